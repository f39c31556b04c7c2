"""The 'nearest+route' encoding: the 'nearest' values, then PAC's own route hint from the observed scene."""

import numpy as np
import pytest

from lerobot_formation.core.controllers.pac import PACController, PathAwareController
from lerobot_formation.core.controllers.route_pursuit import RoutePursuitController, pursuit_chunk
from lerobot_formation.core.encodings.encoding import world_to_body
from lerobot_formation.core.encodings.obstacle_grid import environment_state
from lerobot_formation.core.episodes.rollout import rollout
from lerobot_formation.core.perception.conditions import Conditions
from lerobot_formation.core.safety.filters import decode_nearest
from lerobot_formation.core.world import navigation
from lerobot_formation.core.world.presets import scene_preset
from lerobot_formation.core.world.sampling import sample_scenes
from lerobot_formation.core.world.scenes import FAR


def _scene(rng, n, M=16):
    obs = np.zeros((1, M, 3))
    obs[..., :2] = FAR
    obs[0, :n, :2] = rng.uniform(-1, 7, (n, 2))
    obs[0, :n, 2] = rng.uniform(0.2, 1.0, n)
    mask = np.arange(M)[None] < n
    return obs, mask, np.array([[6.5, 6.0]]), np.array([[0.0, 0.0, 0.3]])


@pytest.mark.parametrize("n", [0, 1, 5, 12, 13, 16])
def test_route_encoding_holds_nearest_then_five_values_for_any_count(n):
    obs, mask, goal, pose = _scene(np.random.default_rng(n), n)
    route = environment_state(obs, mask, goal, "nearest+route", pose=pose)
    nearest = environment_state(obs, mask, goal, "nearest", pose=pose)
    assert route.shape == (1, 55) and route.dtype == np.float32 and np.isfinite(route).all()
    np.testing.assert_array_equal(route[:, :50], nearest)
    _, _, seen = decode_nearest(route[:, :50], 12)
    assert seen.sum() == min(n, 12)
    assert route[0, 54] in (0.0, 1.0)


def test_route_is_pacs_carrot_and_path_check_on_the_same_scene():
    scenes = sample_scenes(np.arange(40), scene_preset("wide"))
    pose = scenes.start.copy()
    pose[:, :2] += np.random.default_rng(0).uniform(-0.5, 0.5, (40, 2))
    env = environment_state(scenes.obstacles, scenes.mask, scenes.goal, "nearest+route", pose=pose)
    pac = PathAwareController()
    pac.reset(scenes.obstacles, scenes.goal)
    pac.field_command(pose)
    carrot = world_to_body(pac.ctg.carrot(pose[:, :2], 5)[:, None], pose)[:, 0]
    np.testing.assert_allclose(env[:, 50:52], carrot, atol=1e-5)
    np.testing.assert_array_equal(env[:, 54] > 0.5, pac.blocked)
    assert 0 < pac.blocked.sum() < 40  # both cases occur


def test_route_sees_only_the_observed_obstacles():
    """A 13th obstacle beyond the 12 observed ones does not enter the route (nothing privileged)."""
    obs, mask, goal, pose = _scene(np.random.default_rng(3), 13)
    obs[0, 12] = [30.0, 30.0, 1.0]  # the farthest: unobserved
    a = environment_state(obs, mask, goal, "nearest+route", pose=pose)
    obs[0, 12] = [31.0, 29.0, 0.5]
    b = environment_state(obs, mask, goal, "nearest+route", pose=pose)
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("n", [0, 5, 12])
def test_maproute_equals_route_with_no_more_obstacles_than_slots(n):
    """``nearest+maproute`` is ``nearest+route`` value for value where the map holds 12 obstacles or fewer."""
    obs, mask, goal, pose = _scene(np.random.default_rng(10 + n), n)
    np.testing.assert_array_equal(
        environment_state(obs, mask, goal, "nearest+maproute", pose=pose),
        environment_state(obs, mask, goal, "nearest+route", pose=pose),
    )


def test_maproute_plans_on_every_map_obstacle():
    """A bend's scene (25-29 obstacles): the same 50 'nearest' values; the route of ``nearest+maproute``
    is PAC's carrot on the whole map, which the 12 nearest of ``nearest+route`` miss somewhere."""
    scenes = sample_scenes(np.arange(12), scene_preset("bend"))
    assert scenes.mask.sum(axis=1).min() > 12
    pose = scenes.start
    whole = environment_state(scenes.obstacles, scenes.mask, scenes.goal, "nearest+maproute", pose=pose)
    near = environment_state(scenes.obstacles, scenes.mask, scenes.goal, "nearest+route", pose=pose)
    np.testing.assert_array_equal(whole[:, :50], near[:, :50])
    pac = PathAwareController()
    pac.reset(scenes.obstacles, scenes.goal)
    pac.field_command(pose)
    carrot = world_to_body(pac.ctg.carrot(pose[:, :2], 5)[:, None], pose)[:, 0]
    np.testing.assert_allclose(whole[:, 50:52], carrot, atol=1e-5)
    assert not np.allclose(near[:, 50:54], whole[:, 50:54], atol=1e-3)


def test_route_pursuit_takes_the_checkpoints_route_hint():
    """The bench's route pursuit plans on the whole map where its checkpoint observes ``nearest+maproute``."""
    from types import SimpleNamespace

    from lerobot_formation.core.controllers.route_pursuit import make_route_pursuit
    from lerobot_formation.core.world.dynamics import FormationParams

    def bundle(encoding):
        return (SimpleNamespace(config=SimpleNamespace(obstacle_encoding=encoding)), None, None)

    params = FormationParams()
    assert not make_route_pursuit("route-pursuit", params).config.whole_map
    assert not make_route_pursuit("route-pursuit", params, None, bundle("nearest+route")).config.whole_map
    assert make_route_pursuit("route-pursuit", params, None, bundle("nearest+maproute")).config.whole_map


def test_route_near_carrot_leads_around_a_blocker():
    obs = np.array([[[3.0, 0.0, 0.8]]])
    mask = np.ones((1, 1), bool)
    goal = np.array([[7.0, 0.0]])
    pose = np.array([[0.5, 0.0, 0.0]])  # facing the goal through the obstacle
    env = environment_state(obs, mask, goal, "nearest+route", pose=pose)
    assert env[0, 54] == 1.0  # blocked
    far_b = env[0, 52:54]  # body frame: x right, y ahead
    assert abs(far_b[0]) > 0.5  # the 3 m carrot steps sideways off the straight line
    assert far_b[1] > 1.0  # and still leads forward


def test_pac_command_does_not_depend_on_the_batch():
    """Each scene's field is its own: a scene's demonstration is the same alone or in any batch."""
    scenes = sample_scenes(np.arange(12), scene_preset("wide"))
    pose = scenes.start.copy()
    together = PathAwareController()
    together.reset(scenes.obstacles, scenes.goal)
    batch = together.command(pose)
    for b in (0, 5, 11):
        alone = PathAwareController()
        alone.reset(scenes.obstacles[b : b + 1], scenes.goal[b : b + 1])
        np.testing.assert_array_equal(alone.command(pose[b : b + 1])[0], batch[b])


@pytest.mark.parametrize("controller, moving", [("route-pursuit", 0), ("pac", 0), ("pac", 1)])
def test_route_hint_field_is_rebuilt_only_when_the_map_changes(monkeypatch, controller, moving):
    """Under obstacle noise (and moving obstacles) the observed obstacles change at every step, but
    the route hint's cost-to-go (route pursuit's, or the ``nearest+route`` observations recorded
    beside PAC, which builds its field on the same map) is built on ``Perception.map_obstacles``: once
    per map version of a team (scenes of at most 12 obstacles: the nearest selection is the whole map)."""
    builds = []

    def counting(obstacles, goal, **kwargs):
        builds.append(obstacles.copy())
        return cost_to_go(obstacles, goal, **kwargs)

    cost_to_go = navigation.cost_to_go
    monkeypatch.setattr(navigation, "cost_to_go", counting)
    monkeypatch.setattr(navigation, "_SCENE_FIELDS", type(navigation._SCENE_FIELDS)())
    views = []

    class Spy:
        def __init__(self, inner):
            self.inner, self.name = inner, inner.name

        def reset(self, view):
            self.inner.reset(view)

        def act(self, view, idx):
            views.append((idx, view[np.arange(len(view))]))
            return self.inner.act(view, idx)

    scenes = sample_scenes([1_000_000, 1_000_001, 1_000_002])
    cond = Conditions(obstacle_noise=0.05, sensing_range=1.5, moving_obstacles=moving, obstacle_speed=0.3)
    inner = RoutePursuitController() if controller == "route-pursuit" else PACController()
    record = None if controller == "route-pursuit" else ("nearest+route", None)
    rec = rollout(scenes, Spy(inner), max_steps=80, conditions=cond, record_observations=record)
    assert record is None or rec.observations["environment_state"].shape[-1] == 55
    versions, steps, moved = set(), 0, 0
    last: dict[tuple, tuple] = {}
    for idx, view in views:
        for r, b in enumerate(idx):
            steps += 1
            key = (int(b), int(view.map_version[r]))
            seen = view.obstacles[r][view.mask[r]]
            if key in last:  # the same map version: the same map, though the observed obstacles moved
                np.testing.assert_array_equal(view.map_obstacles[r], last[key][0])
                moved += not np.array_equal(seen, last[key][1])
            else:  # a new map: the static observed obstacles of this step, moving ones padding
                static = ~np.any(view.obstacle_velocity[r] != 0, axis=-1)
                np.testing.assert_array_equal(view.map_obstacles[r][static], view.obstacles[r][static])
                assert (view.map_obstacles[r][~static] == [FAR, FAR, 0.0]).all()
                last[key] = (view.map_obstacles[r].copy(), seen)
            last[key] = (last[key][0], seen)
            versions.add(key)
    assert steps > 100 and moved > steps / 2  # the noise moves the observed obstacles
    if moving:  # a moving obstacle was observed, and left off the map
        assert any((v.obstacle_velocity != 0).any() for _, v in views)
    # one field per team and map version (fewer when a map repeats), not one per step
    assert len({b for b, _ in versions}) <= len(builds) <= len(versions) < steps / 5


def test_pursuit_chunk_follows_the_hints_polyline():
    """Route pursuit's chunk from the hint's two carrots (body frame): straight down a straight route
    at cruise speed; towards a carrot on the left it turns left, and it is the command route pursuit
    itself sends at the first step."""
    from lerobot_formation.core.controllers.route_pursuit import RoutePursuitConfig, pursuit_command

    cfg = RoutePursuitConfig()
    route = np.array([[0.0, 1.0, 0.0, 3.0], [-0.8, 0.6, -2.5, 1.5]])
    goal = np.array([[0.0, 8.0], [-4.0, 4.0]])
    chunk = pursuit_chunk(route, goal, 15, 0.1, 1.5)
    assert chunk.shape == (2, 15, 2)
    np.testing.assert_allclose(chunk[0], np.tile([cfg.v_max, 0.0], (15, 1)), atol=1e-12)
    first = pursuit_command(route[1:, :2], np.linalg.norm(goal[1:], axis=-1), cfg, 1.5)
    np.testing.assert_allclose(chunk[1, 0], first[0])
    assert (chunk[1, :, 1] > 0).all()  # left all along: the far carrot is further left
    # within r_goal of the goal it aims at the goal itself
    near_goal = pursuit_chunk(np.array([[0.0, 1.0, 0.0, 3.0]]), np.array([[0.3, 0.0]]), 3, 0.1, 1.5)
    assert near_goal[0, 0, 1] < 0  # the goal is to the right
    # from another start pose (the safety layer's lookahead): the same as pursuing the carrots and
    # the goal seen from that pose
    start = np.array([[0.4, 0.7, 2.1], [-0.3, 0.2, 0.9]])
    seen = world_to_body(np.concatenate([route.reshape(2, 2, 2), goal[:, None]], axis=1), start)
    np.testing.assert_allclose(
        pursuit_chunk(route, goal, 15, 0.1, 1.5, start=start),
        pursuit_chunk(seen[:, :2].reshape(2, 4), seen[:, 2], 15, 0.1, 1.5),
        atol=1e-9,
    )


def test_pursuit_chunk_is_pursuit_command_rolled_through_the_unicycle():
    """``pursuit_chunk`` writes its loop out on coordinate arrays; its numbers are, bit for bit, those of
    the documented steps: aim at the near carrot until within half its starting distance, then the far
    one, the goal within ``r_goal``; ``pursuit_command`` on the aim in the body frame
    (``world_to_body``); one ``dynamics.step_midpoint``."""
    from lerobot_formation.core.controllers.route_pursuit import RoutePursuitConfig, pursuit_command
    from lerobot_formation.core.encodings.encoding import BODY_POSE
    from lerobot_formation.core.world.dynamics import step_midpoint

    cfg = RoutePursuitConfig()
    rng = np.random.default_rng(3)
    for trial in range(40):
        B = int(rng.integers(1, 50))
        route = rng.uniform(-3, 3, (B, 4)) * rng.choice([0.2, 1.0, 3.0])
        goal = rng.uniform(-5, 5, (B, 2)) * rng.choice([0.05, 0.3, 1.0])
        start = (
            None if trial % 2 else np.concatenate([rng.uniform(-2, 2, (B, 2)), rng.uniform(-4, 4, (B, 1))], 1)
        )
        pose = np.tile(BODY_POSE, (B, 1)) if start is None else start.copy()
        near, far = route[:, :2], route[:, 2:]
        switch = 0.5 * np.linalg.norm(near - pose[:, :2], axis=-1)
        passed = np.zeros(B, dtype=bool)
        expected = np.zeros((B, 20, 2))
        for k in range(20):
            passed |= np.linalg.norm(near - pose[:, :2], axis=-1) < switch
            d_goal = np.linalg.norm(goal - pose[:, :2], axis=-1)
            aim = np.where((d_goal < cfg.r_goal)[:, None], goal, np.where(passed[:, None], far, near))
            expected[:, k] = pursuit_command(world_to_body(aim, pose), d_goal, cfg, 1.5)
            pose = step_midpoint(pose, expected[:, k], 0.1)
        assert np.array_equal(pursuit_chunk(route, goal, 20, 0.1, 1.5, start=start), expected)
