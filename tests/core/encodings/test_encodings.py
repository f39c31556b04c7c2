"""Obstacle encodings: the registry, sizes and names, and the egocentric 'nearest' round trip."""

import numpy as np
import pytest

from lerobot_formation.core.encodings.encoding import world_to_body
from lerobot_formation.core.encodings.obstacle_grid import (
    ENCODING_REGISTRY,
    ENCODINGS,
    environment_state,
    environment_state_dim,
    get_encoding,
)
from lerobot_formation.core.safety.filters import decode_nearest
from lerobot_formation.core.world.dynamics import rotate_body
from lerobot_formation.core.world.presets import SCENE_PRESETS
from lerobot_formation.core.world.sampling import sample_scenes
from lerobot_formation.core.world.scenes import FAR


def _random_scene(rng, n, M=16):
    obs = np.zeros((1, M, 3))
    obs[..., :2] = FAR
    obs[0, :n, :2] = rng.uniform(-6, 6, (n, 2))
    obs[0, :n, 2] = rng.uniform(0.2, 1.0, n)
    mask = np.arange(M)[None] < n
    goal = rng.uniform(-8, 8, (1, 2))
    pose = np.array([[*rng.uniform(-2, 2, 2), rng.uniform(-np.pi, np.pi)]])
    return obs, mask, goal, pose


def test_registry_sizes_and_names():
    assert set(ENCODINGS) == {
        "grid",
        "grid+list",
        "nearest",
        "nearest+route",
        "nearest+maproute",
        "nearest+velocity",
        "nearest+route+velocity",
        "nearest+moverroute+velocity",
    }
    for name in ENCODING_REGISTRY:
        enc = get_encoding(name)  # "nearest+route" lives in its own file, imported here
        assert len(enc.names(enc.slots(None))) == enc.dim(None) == environment_state_dim(name)
    assert environment_state_dim("grid") == 51
    assert environment_state_dim("grid+list") == 66
    assert environment_state_dim("nearest") == 50
    assert environment_state_dim("nearest", 3) == 14
    assert environment_state_dim("nearest+route") == 55
    assert environment_state_dim("nearest+maproute") == 55
    assert environment_state_dim("nearest+velocity") == 74
    assert environment_state_dim("nearest+velocity", 3) == 20
    assert environment_state_dim("nearest+route+velocity") == 79
    assert environment_state_dim("nearest+moverroute+velocity") == 79
    with pytest.raises(ValueError, match="obstacle encoding must be one of"):
        get_encoding("gird")


def test_route_velocity_is_the_velocity_encoding_then_the_route_hint():
    """``nearest+route+velocity``: the rows and velocities of ``nearest+velocity``, then the 5 route
    values of ``nearest+route`` planned on the map snapshot (not on the current noisy obstacles)."""
    rng = np.random.default_rng(3)
    obstacles, mask, goal, pose = _random_scene(rng, 9)
    velocity = rng.normal(0, 0.3, (1, 16, 2))
    snapshot = obstacles.copy()
    snapshot[0, 0] = [*(0.7 * pose[0, :2] + 0.3 * goal[0]), 1.0]  # the map blocks the straight way
    both = environment_state(
        obstacles,
        mask,
        goal,
        "nearest+route+velocity",
        pose=pose,
        obstacle_velocity=velocity,
        map_obstacles=snapshot,
    )
    with_velocity = environment_state(
        obstacles, mask, goal, "nearest+velocity", pose=pose, obstacle_velocity=velocity
    )
    route = environment_state(obstacles, mask, goal, "nearest+route", pose=pose, map_obstacles=snapshot)
    unmapped = environment_state(obstacles, mask, goal, "nearest+route", pose=pose)
    assert both.shape == (1, 79) and both.dtype == np.float32
    np.testing.assert_array_equal(both[:, :74], with_velocity)
    np.testing.assert_array_equal(both[:, 74:], route[:, 50:])
    assert not np.array_equal(route[:, 50:54], unmapped[:, 50:54])  # the snapshot mattered
    names = get_encoding("nearest+route+velocity").names(12)
    assert (
        names[50:52] == ["near_0_vbx", "near_0_vby"]
        and names[74:] == get_encoding("nearest+route").names(12)[50:]
    )


def test_body_frame_is_inverse_of_rotate_body():
    rng = np.random.default_rng(0)
    pose = np.array([[1.0, -2.0, 0.7], [0.0, 0.0, np.pi / 2]])
    offsets = rng.normal(size=(2, 5, 2))
    world = rotate_body(offsets, pose[:, 2][:, None].repeat(5, 1)) + pose[:, None, :2]
    np.testing.assert_allclose(world_to_body(world, pose), offsets, atol=1e-12)


@pytest.mark.parametrize("n", [0, 1, 5, 7, 12, 13, 16])
def test_nearest_round_trips_any_obstacle_count(n):
    """Every obstacle up to 12 comes back exactly (in the world frame); beyond 12 the nearest 12."""
    rng = np.random.default_rng(n)
    obs, mask, goal, pose = _random_scene(rng, n)
    env = environment_state(obs, mask, goal, "nearest", pose=pose)
    assert env.shape == (1, 50) and env.dtype == np.float32
    goal_b, obs_b, mask_b = decode_nearest(env, 12)
    back_goal = rotate_body(goal_b, pose[:, 2]) + pose[:, :2]
    np.testing.assert_allclose(back_goal, goal, atol=1e-4)
    k = min(n, 12)
    assert mask_b.sum() == k
    centres = rotate_body(obs_b[0, :k, :2], np.full(k, pose[0, 2])) + pose[0, :2]
    surface = np.linalg.norm(obs[0, :n, :2] - pose[0, :2], axis=-1) - obs[0, :n, 2]
    nearest = np.argsort(surface, kind="stable")[:k]
    np.testing.assert_allclose(centres, obs[0, nearest, :2], atol=1e-4)
    np.testing.assert_allclose(obs_b[0, :k, 2], obs[0, nearest, 2], atol=1e-6)
    got_surface = np.linalg.norm(obs_b[0, :k, :2], axis=-1) - obs_b[0, :k, 2]
    assert np.all(np.diff(got_surface) >= -1e-5)  # nearest first


def test_grid_list_refuses_more_obstacles_than_rows():
    rng = np.random.default_rng(1)
    obs, mask, goal, pose = _random_scene(rng, 7)
    with pytest.raises(ValueError, match="7 obstacles, more than the 5 rows"):
        environment_state(obs, mask, goal, "grid+list")
    assert environment_state(obs, mask, goal, "grid+list", max_obstacles=7).shape == (1, 51 + 21)


def test_nearest_needs_the_pose():
    rng = np.random.default_rng(2)
    obs, mask, goal, _ = _random_scene(rng, 3)
    with pytest.raises(ValueError, match="needs the midpoint pose"):
        environment_state(obs, mask, goal, "nearest")


def test_presets_are_deterministic_valid_and_cover_the_ranges():
    seeds = np.arange(1000, 1010)  # a scene is drawn from its own seed: ten show determinism
    for cfg in SCENE_PRESETS.values():
        a, b = sample_scenes(seeds, cfg), sample_scenes(seeds, cfg)
        for key in ("obstacles", "mask", "goal", "start"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
        assert a.obstacles.shape[1] == cfg.max_obstacles
    wide = sample_scenes(np.arange(40), SCENE_PRESETS["wide"])  # 0-11 obstacles of 0.22-0.97 m
    counts = wide.mask.sum(axis=1)
    assert counts.min() <= 2 and counts.max() >= 10
    r = wide.obstacles[..., 2][wide.mask]
    assert r.min() < 0.3 and r.max() > 0.85
    assert (np.abs(wide.goal - 5.0) > 1e-9).any(axis=1).mean() > 0.4  # other goals
    assert (np.abs(wide.start[:, 2] - np.pi / 2) > 1e-9).mean() > 0.4  # other start headings


def test_mover_route_is_route_pursuits_route():
    """``nearest+moverroute+velocity``: the values of ``nearest+route+velocity`` without movers; with a
    mover observed, route pursuit's own route (its first command, decoded from the hint, is route
    pursuit's command), which the plain hint (planned on the map, movers left out) is not."""
    from lerobot_formation.core.controllers.route_pursuit import RoutePursuitController, pursuit_chunk
    from lerobot_formation.core.perception.conditions import Perception

    rng = np.random.default_rng(5)
    obstacles, mask, goal, pose = _random_scene(rng, 9)
    snapshot = obstacles.copy()
    velocity = np.zeros((1, 16, 2))
    still = dict(pose=pose, obstacle_velocity=velocity, map_obstacles=snapshot)
    np.testing.assert_array_equal(
        environment_state(obstacles, mask, goal, "nearest+moverroute+velocity", **still),
        environment_state(obstacles, mask, goal, "nearest+route+velocity", **still),
    )
    # a mover 1.2 m ahead on the straight way to the goal, absent from the map
    ahead = pose[0, :2] + 1.2 * (goal[0] - pose[0, :2]) / np.linalg.norm(goal[0] - pose[0, :2])
    obstacles[0, 9] = [*ahead, 0.5]
    mask = mask.copy()
    mask[0, 9] = True
    velocity[0, 9] = [0.3, -0.2]
    snapshot[0, 9] = [1e3, 1e3, 0.0]  # movers are padding on the map
    moved = dict(pose=pose, obstacle_velocity=velocity, map_obstacles=snapshot)
    enc = get_encoding("nearest+moverroute+velocity")
    state = environment_state(obstacles, mask, goal, "nearest+moverroute+velocity", **moved)
    plain = environment_state(obstacles, mask, goal, "nearest+route+velocity", **moved)
    route, goal_body = enc.route_hint(state)
    assert not np.allclose(route, enc.route_hint(plain)[0])
    view = Perception(
        pose, np.zeros((1, 3)), obstacles, mask, velocity, goal, np.zeros(1, np.int64), snapshot
    )
    controller = RoutePursuitController()
    command = controller.act(view, np.arange(1))
    first = pursuit_chunk(route, goal_body, 1, 0.1, controller.params.omega_max)[:, 0]
    np.testing.assert_allclose(first, command, atol=1e-5)
