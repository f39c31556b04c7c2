"""MPPI baseline: reaches the goal, is reproducible, respects bounds and the live-subset interface."""

from __future__ import annotations

import numpy as np

from lerobot_formation.core.controllers.mppi import MPPIConfig, MPPIController, bilinear
from lerobot_formation.core.episodes.rollout import SUCCESS, rollout
from lerobot_formation.core.perception.conditions import Perception
from lerobot_formation.core.world.dynamics import FormationParams, initial_state, rotate_body
from lerobot_formation.core.world.geometry import point_clearance
from lerobot_formation.core.world.sampling import sample_scenes
from lerobot_formation.core.world.scene_files import scenes_from_list

FAST = MPPIConfig(num_samples=64, horizon=20)


def test_empty_scene_reaches_goal():
    scenes = scenes_from_list([{"obstacles": [], "goal": [5, 5]}])
    rec = rollout(scenes, MPPIController(FAST))
    assert rec.outcome[0] == SUCCESS
    # 7.07 m at up to 0.6 m/s: at least 118 steps; a straight-ish run should not take much longer.
    assert rec.steps[0] < 200
    assert np.linalg.norm(rec.poses[0, rec.steps[0], :2] - [5, 5]) <= FormationParams().goal_tolerance


def test_random_scenes_reach_goal_with_defaults():
    scenes = sample_scenes([1_000_000, 1_000_001])
    rec = rollout(scenes, MPPIController())
    assert (rec.outcome == SUCCESS).all(), rec.outcome


def test_same_seed_same_actions():
    scenes = sample_scenes([1_000_000, 1_000_001, 1_000_002])
    runs = []
    for seed in (7, 7, 8):
        ctl = MPPIController(MPPIConfig(num_samples=32, horizon=10, seed=seed))
        ctl.reset(Perception.exact(scenes, initial_state(scenes.start)))
        state = initial_state(scenes.start)
        idx = np.arange(3)
        runs.append(np.stack([ctl.act(Perception.exact(scenes, state), idx) for _ in range(4)]))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(runs[0], runs[2])


def test_reset_restarts_the_noise():
    scenes = sample_scenes([1_000_000])
    ctl = MPPIController(MPPIConfig(num_samples=32, horizon=10, seed=3))
    state, idx = initial_state(scenes.start), np.arange(1)
    ctl.reset(Perception.exact(scenes, initial_state(scenes.start)))
    a = ctl.act(Perception.exact(scenes, state), idx)
    ctl.reset(Perception.exact(scenes, initial_state(scenes.start)))
    np.testing.assert_array_equal(a, ctl.act(Perception.exact(scenes, state), idx))


def test_actions_respect_bounds():
    params = FormationParams()
    scenes = sample_scenes(np.arange(1_000_000, 1_000_004))
    ctl = MPPIController(MPPIConfig(num_samples=32, horizon=10, sigma_v=5.0, sigma_omega=20.0, v_cruise=2.0))
    ctl.reset(Perception.exact(scenes, initial_state(scenes.start)))
    state, idx = initial_state(scenes.start), np.arange(4)
    for _ in range(5):
        a = ctl.act(Perception.exact(scenes, state), idx)
        assert a.shape == (4, 2) and np.isfinite(a).all()
        assert (a[:, 0] >= 0).all() and (a[:, 0] <= params.v_max).all()
        assert (np.abs(a[:, 1]) <= params.omega_max).all()
        assert (ctl.nominal[..., 0] >= 0).all() and (ctl.nominal[..., 0] <= params.v_max).all()
        assert (np.abs(ctl.nominal[..., 1]) <= params.omega_max).all()


def test_subset_idx_shapes_and_bookkeeping():
    scenes = sample_scenes(np.arange(1_000_000, 1_000_005))
    ctl = MPPIController(MPPIConfig(num_samples=16, horizon=8))
    ctl.reset(Perception.exact(scenes, initial_state(scenes.start)))
    full = initial_state(scenes.start)
    before = ctl.nominal.copy()
    idx = np.array([1, 4])
    a = ctl.act(Perception.exact(scenes, full)[idx], idx)
    assert a.shape == (2, 2)
    assert ctl.nominal.shape == (5, 8, 2)
    untouched = np.array([0, 2, 3])
    np.testing.assert_array_equal(ctl.nominal[untouched], before[untouched])
    np.testing.assert_array_equal(ctl.prev_action[idx], a)
    assert not np.array_equal(ctl.nominal[idx], before[idx])
    assert ctl.act(Perception.exact(scenes, full)[[3]], np.array([3])).shape == (1, 2)


def test_footprint_matches_pac_geometry():
    """The fast float32 footprint equals rotate_body(template) + point_clearance - agent radius."""
    scenes = sample_scenes(np.arange(1_000_000, 1_000_003))
    ctl = MPPIController()
    rng = np.random.default_rng(0)
    pose = np.concatenate([rng.uniform(0, 6, (3, 7, 2)), rng.uniform(-np.pi, np.pi, (3, 7, 1))], axis=-1)
    got = ctl.footprint_clearance(pose, scenes.obstacles)
    tmpl = ctl.template
    agents = rotate_body(np.broadcast_to(tmpl, (3, 7, len(tmpl), 2)), np.repeat(pose[..., 2:], len(tmpl), -1))
    agents = agents + pose[..., None, :2]
    want = point_clearance(agents.reshape(3, -1, 2), scenes.obstacles).reshape(3, 7, -1).min(-1) - 0.1
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_bilinear_matches_grid_values():
    scenes = sample_scenes([1_000_000, 1_000_001])
    ctl = MPPIController()
    ctl.reset(Perception.exact(scenes, initial_state(scenes.start)))
    ctg = ctl.ctg
    ij = np.array([[[10, 20], [31, 40]], [[25, 25], [50, 12]]])  # (B, P, 2) grid nodes
    xy = ctg.origin + ctg.resolution * ij
    want = ctg.value[np.arange(2)[:, None], ij[..., 0], ij[..., 1]]
    np.testing.assert_allclose(bilinear(ctg, xy), want, rtol=1e-9)
