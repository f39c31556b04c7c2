"""Each realistic condition (``core.perception.conditions``) does what docs/conditions.md says."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import Spy

from lerobot_formation.core.controllers.mppi import MPPIConfig, MPPIController
from lerobot_formation.core.controllers.pac import PACController
from lerobot_formation.core.encodings.obstacle_grid import environment_state
from lerobot_formation.core.episodes.rollout import COLLISION, Teams, rollout
from lerobot_formation.core.perception.conditions import (
    CONDITION_FIELDS,
    CONDITION_TYPES,
    ZONE_RADIUS,
    Conditions,
    Perception,
    condition_help,
    condition_kind,
    obstacle_velocities,
    scene_bounds,
)
from lerobot_formation.core.world.dynamics import FormationParams, rate_limit
from lerobot_formation.core.world.geometry import obstacle_gaps
from lerobot_formation.core.world.sampling import sample_scenes
from lerobot_formation.core.world.scene_files import scenes_from_list
from lerobot_formation.core.world.scenes import FAR

# An obstacle right of the straight line x = 0, far from the start: a team driving straight up
# passes it at 1.5 m (its right leader at 1.0 m of its surface) around y = 5.
BESIDE = {"obstacles": [[2.0, 5.0, 0.5]], "goal": [0.0, 10.0], "start": [0.0, 0.0, np.pi / 2]}


class Straight:
    """Drives straight ahead at v, and keeps every view it is given."""

    name = "straight"

    def __init__(self, v: float = 0.5):
        self.v, self.views = v, []

    def reset(self, view: Perception) -> None:
        self.views.append(view)

    def act(self, view: Perception, idx: np.ndarray) -> np.ndarray:
        self.views.append(view)
        return np.tile([self.v, 0.0], (len(idx), 1))


def test_validation_names_field_and_value():
    assert CONDITION_FIELDS[0] == "sensing_range" and "obstacle_speed" in CONDITION_FIELDS
    assert not Conditions().enabled and Conditions(action_delay=1).enabled
    assert Conditions(pose_noise=0.1).changed() == {"pose_noise": 0.1}
    for kwargs, words in (
        (dict(sensing_range=0.0), "sensing_range must be a finite number > 0, got 0.0"),
        (dict(obstacle_noise=-1), "obstacle_noise must be a finite number >= 0, got -1"),
        (dict(pose_noise=float("nan")), "pose_noise"),
        (dict(action_delay=1.5), "action_delay must be an integer >= 0, got 1.5"),
        (dict(moving_obstacles=-2), "moving_obstacles must be an integer >= 0, got -2"),
        (dict(moving_obstacles=2), "needs obstacle_speed > 0"),
        (dict(max_linear_accel=-1.0), "max_linear_accel"),
        (dict(obstacle_memory="yes"), "obstacle_memory must be true or false"),
        (dict(action_delay=1001), "action_delay must be <= 1000 control steps, got 1001"),
        (dict(obstacle_speed=None), "obstacle_speed must be a finite number >= 0, got None"),
    ):
        with pytest.raises(ValueError, match=words.replace("(", r"\(")):
            Conditions(**kwargs)


def test_each_condition_is_declared_once_with_its_help_and_bounds():
    """Every field of ``Conditions`` carries its help, unit and bounds (``condition``), which the env
    config and the CLI flags show and ``__post_init__`` checks; its kind is its annotation."""
    off = Conditions()
    for name in CONDITION_FIELDS:
        meta = Conditions.__dataclass_fields__[name].metadata
        assert meta["help"].strip() and meta["help"] in condition_help(name)
        if meta["unit"]:
            assert condition_help(name).startswith(f"[{meta['unit']}] ")
        kind = condition_kind(name)
        assert kind in (bool, int, float)
        default = getattr(off, name)
        assert default is None or type(default) is kind, name
        if default is None:
            assert type(None) in getattr(CONDITION_TYPES[name], "__args__", ())
        for bound, bad in (("gt", 0), ("ge", -1)):  # at a strict bound, or one below an inclusive one
            if meta[bound] is not None:
                value = kind(meta[bound] + bad)
                with pytest.raises(ValueError, match=f"conditions: {name} must be .* got {value!r}"):
                    Conditions(**{name: value})
        if meta["le"] is not None:
            with pytest.raises(ValueError, match=f"conditions: {name} must be <= {meta['le']}"):
                Conditions(**{name: kind(meta["le"] + 1)})
        if kind is not bool:
            with pytest.raises(ValueError, match=f"conditions: {name} must be .*, got 'x'"):
                Conditions(**{name: "x"})


@pytest.mark.parametrize("memory", [True, False])
def test_sensing_range_hides_an_obstacle_until_sensed(memory):
    scenes = scenes_from_list([BESIDE])
    ctrl = Straight()
    rng = 1.2
    rec = rollout(
        scenes, ctrl, max_steps=150, conditions=Conditions(sensing_range=rng, obstacle_memory=memory)
    )
    seen = np.array([bool(v.mask[0, 0]) for v in ctrl.views[1:]])  # the view at each act, step t = 0..
    first = int(np.argmax(seen))
    assert 0 < first < 150 and not seen[:first].any()
    unseen = ctrl.views[first]
    np.testing.assert_array_equal(unseen.obstacles[0, 0], [FAR, FAR, 0.0])
    np.testing.assert_array_equal(ctrl.views[first + 1].obstacles[0, 0], [2.0, 5.0, 0.5])
    assert rec.seen_step[0, 0] == first
    # it appears at the first step an agent is within range of its surface
    gaps = [obstacle_gaps(rec.positions[:, t], scenes.obstacles)[0, :, 0].min() for t in range(first + 1)]
    assert gaps[first] <= rng and min(gaps[:first]) > rng
    if memory:
        assert seen[first:].all()
    else:  # forgotten once every agent is out of range again
        assert not seen[-1]


def test_every_controller_sees_only_sensed_obstacles():
    scenes = sample_scenes([1_000_000, 1_000_001, 1_000_002])
    cond = Conditions(sensing_range=1.0)
    for inner in (PACController(), MPPIController(MPPIConfig(num_samples=16, horizon=6))):
        spy = Spy(inner)
        rec = rollout(scenes, spy, max_steps=60, conditions=cond)
        assert (rec.seen_step == -1).sum() > 0  # some obstacle is never sensed in these 60 steps
        live = np.arange(len(scenes))
        for t, view in enumerate(spy.views[1:]):
            rows = live if len(view) == len(live) else live[: len(view)]
            for r, b in enumerate(rows):
                unseen = (rec.seen_step[b] < 0) | (rec.seen_step[b] > t)
                assert not view.mask[r][unseen].any()
                assert (view.obstacles[r][unseen][:, 2] == 0).all()
        if isinstance(inner, PACController):  # PAC's own copy is the perceived one too
            never = (rec.seen_step < 0) & scenes.mask
            assert not np.isin(scenes.obstacles[:, :, 0][never], inner.pac.obstacles[..., 0]).any()


def test_noise_has_the_stated_spread_and_repeats():
    scenes = sample_scenes([1_000_000, 1_000_001])
    cond = Conditions(obstacle_noise=0.1, pose_noise=0.05)

    def errors(batch):
        teams = Teams(batch, conditions=cond)
        obs_err, pose_err = [], []
        for _ in range(300):
            v = teams.perceive()
            obs_err.append((v.obstacles - teams.scenes.obstacles)[v.mask])
            pose_err.append(v.pose - teams.state.pose)
            teams.step(np.zeros((len(batch), 2)))  # standing still
        return np.concatenate(obs_err), np.stack(pose_err)

    obs_err, pose_err = errors(scenes)
    assert np.std(obs_err, axis=0) == pytest.approx([0.1, 0.1, 0.1], rel=0.08)
    assert np.abs(obs_err.mean(axis=0)).max() < 0.01
    assert np.std(pose_err.reshape(-1, 3), axis=0) == pytest.approx([0.05] * 3, rel=0.08)
    again, _ = errors(scenes)
    np.testing.assert_array_equal(obs_err, again)  # the same seed: the same draws
    # a team's draws do not depend on its batch
    alone = Teams(scenes[1:], conditions=cond).perceive()
    both = Teams(scenes, conditions=cond).perceive()
    np.testing.assert_array_equal(alone.obstacles[0], both.obstacles[1])
    np.testing.assert_array_equal(alone.pose[0], both.pose[1])
    other = Teams(sample_scenes([1_000_005, 1_000_001]), conditions=cond).perceive()
    np.testing.assert_array_equal(other.pose[1], both.pose[1])


def test_action_noise_spread():
    scenes = sample_scenes([1_000_000])
    teams = Teams(scenes, conditions=Conditions(action_noise=0.2))
    ratios = []
    for _ in range(400):
        t = teams.step(np.array([[0.3, 0.5]]))
        ratios.append(t.action[0] / [0.3, 0.5] - 1)
    assert np.std(ratios, axis=0) == pytest.approx([0.2, 0.2], rel=0.12)


@pytest.mark.parametrize("k", [1, 3])
def test_delay_shifts_executed_commands_by_k(k):
    scenes = sample_scenes([1_000_000, 1_000_001])
    teams = Teams(scenes, conditions=Conditions(action_delay=k))
    commands = np.random.default_rng(0).uniform([0.0, -1.0], [0.6, 1.0], size=(12, 2, 2))
    executed = np.stack([teams.step(c).action for c in commands])
    np.testing.assert_array_equal(executed[:k], 0.0)  # nothing has arrived yet: the team holds still
    np.testing.assert_array_equal(executed[k:], commands[:-k])


def test_rate_limits_hold():
    params = FormationParams()
    cond = Conditions(max_linear_accel=0.5, max_angular_accel=2.0)
    teams = Teams(sample_scenes([1_000_000]), conditions=cond)
    commands = np.array([[0.6, 1.5], [0.6, -1.5], [0.0, 0.0], [0.6, 1.5]] * 10)[:, None]
    executed = np.concatenate([[[0.0, 0.0]], [teams.step(c).action[0] for c in commands]])
    steps = np.abs(np.diff(executed, axis=0))
    assert (steps[:, 0] <= 0.5 * params.dt + 1e-12).all() and (steps[:, 1] <= 2.0 * params.dt + 1e-12).all()
    assert steps[:, 0].max() == pytest.approx(0.05) and steps[:, 1].max() == pytest.approx(0.2)
    # the equation: toward the command by at most a dt; a component without a limit follows at once
    out = rate_limit(np.array([[0.2, 0.0]]), np.array([[0.6, -1.0]]), 1.0, None, 0.1)
    np.testing.assert_allclose(out, [[0.3, -1.0]])
    # a held command is reached
    teams = Teams(sample_scenes([1_000_000]), conditions=cond)
    for _ in range(20):
        last = teams.step(np.array([[0.4, 1.0]])).action
    np.testing.assert_allclose(last, [[0.4, 1.0]])


def test_moving_obstacle_moves_and_bounces():
    scene = {
        "obstacles": [[3.0, 5.0, 0.5], [-2.0, 3.0, 0.4]],
        "goal": [0.0, 10.0],
        "velocities": [[1.0, 0.0], [0, 0]],
    }
    scenes = scenes_from_list([scene])
    rec = rollout(scenes, Straight(0.0), max_steps=40)  # the scene's velocities: moving without any flag
    x = rec.obstacle_paths[0, :, 0, 0]
    assert x[1] == pytest.approx(3.1)  # 1 m/s for 0.1 s
    hi = scene_bounds(scenes)[0, 2]
    assert hi == pytest.approx(4.5) and x.max() <= hi + 1e-12
    assert np.argmax(x) < 40 and x[-1] < x.max() - 0.5  # it turned back
    np.testing.assert_array_equal(rec.obstacle_paths[0, :, 1], np.tile([-2.0, 3.0], (41, 1)))  # static
    np.testing.assert_array_equal(rec.obstacle_paths[0, :, 0, 1], 5.0)


def test_moving_obstacles_keep_out_of_start_and_goal_zones():
    scenes = sample_scenes(1_000_000 + np.arange(12), None)
    cond = Conditions(moving_obstacles=3, obstacle_speed=0.6)
    vel = obstacle_velocities(scenes, cond)
    speed = np.linalg.norm(vel, axis=-1)
    assert ((speed > 0).sum(axis=1) <= 3).all() and (speed > 0).sum() > 12
    np.testing.assert_allclose(speed[speed > 0], 0.6)
    np.testing.assert_array_equal(vel, obstacle_velocities(scenes, cond))  # from the seeds
    rec = rollout(scenes, Straight(0.0), max_steps=200, conditions=cond)
    moving = speed > 0
    for zone in (scenes.start[:, :2], scenes.goal):
        gap = (
            np.linalg.norm(rec.obstacle_paths - zone[:, None, None], axis=-1)
            - scenes.obstacles[:, None, :, 2]
        )
        assert (
            gap[:, :, :][np.broadcast_to(moving[:, None], gap.shape)].min() >= ZONE_RADIUS - 0.6 * 0.1 - 1e-9
        )


def test_collision_with_a_moving_obstacle_ends_the_episode():
    # crosses the team's straight path at y = 5 when the team gets there (10 s at 0.5 m/s)
    scene = {"obstacles": [[-4.0, 5.0, 0.5]], "goal": [0.0, 10.0], "velocities": [[0.4, 0.0]]}
    scenes = scenes_from_list([scene])
    rec = rollout(scenes, Straight(0.5), max_steps=300)
    assert rec.outcome[0] == COLLISION and 80 < rec.steps[0] < 120
    n = int(rec.steps[0])
    assert np.isnan(rec.obstacle_paths[0, n + 1 :]).all()
    # the same scene with the obstacle standing where it starts: no collision there
    still = scenes_from_list([{**scene, "velocities": [[0.0, 0.0]]}])
    assert rollout(still, Straight(0.5), max_steps=n + 5).outcome[0] != COLLISION


def test_moving_obstacles_velocity_is_observed():
    scene = {"obstacles": [[3.0, 5.0, 0.5]], "goal": [0.0, 10.0], "velocities": [[0.0, -0.5]]}
    teams = Teams(scenes_from_list([scene]), obstacle_encoding="nearest+velocity")
    view = teams.perceive()
    np.testing.assert_array_equal(view.obstacle_velocity[0, 0], [0.0, -0.5])
    env = teams.observe()["environment_state"][0]
    # heading +y: body x is world x, body y is world y
    np.testing.assert_allclose(env[2 + 4 * 12 : 2 + 4 * 12 + 2], [0.0, -0.5], atol=1e-7)
    np.testing.assert_allclose(env[2 + 4 * 12 + 2 :], 0.0)
    # static: zeros; the nearest part is nearest's
    static = environment_state(view.obstacles, view.mask, view.goal, "nearest", pose=view.pose)
    np.testing.assert_array_equal(env[: static.shape[1]], static[0])


def test_records_of_a_conditioned_rollout():
    scenes = sample_scenes([1_000_000, 1_000_001])
    cond = Conditions(
        sensing_range=2.0, obstacle_noise=0.02, action_delay=1, moving_obstacles=1, obstacle_speed=0.2
    )
    rec = rollout(scenes, PACController(), max_steps=100, conditions=cond)
    B, M = scenes.mask.shape
    assert rec.obstacle_paths.shape == (B, 101, M, 2) and rec.seen_step.shape == (B, M)
    assert rec.seen_step.dtype == np.int64 and (rec.seen_step[~scenes.mask] == -1).all()
    np.testing.assert_array_equal(rec.actions[:, 1:3], rec.commands[:, 0:2])  # one step late
    again = rollout(scenes, PACController(), max_steps=100, conditions=cond)
    np.testing.assert_array_equal(rec.poses, again.poses)
    # frame 0 holds the true obstacles where they start
    np.testing.assert_array_equal(rec.obstacle_paths[:, 0], scenes.obstacles[..., :2])


def _mover_gaps(rec, scenes, moving) -> np.ndarray:
    """Surface gaps (steps, n) between each mover and every other real obstacle over a rollout's
    recorded obstacle paths (NaN rows after an episode's end dropped)."""
    B, T, M, _ = rec.obstacle_paths.shape
    r = scenes.obstacles[..., 2]
    gaps = []
    for b in range(B):
        for i in np.flatnonzero(moving[b]):
            others = np.flatnonzero(scenes.mask[b] & (np.arange(M) != i))
            path = rec.obstacle_paths[b]  # (T, M, 2)
            d = np.linalg.norm(path[:, i, None] - path[:, others], axis=-1)
            g = d - r[b, i] - r[b, others]
            gaps.append(g[~np.isnan(g).any(axis=1)].ravel())
    return np.concatenate(gaps)


@pytest.mark.parametrize(
    ("preset", "cond"),
    [
        ("structures", Conditions(moving_obstacles=2, obstacle_speed=0.3)),  # level5's movers
        ("mixed-hard", Conditions(moving_obstacles=4, obstacle_speed=0.8)),
        ("wide", Conditions(moving_obstacles=6, obstacle_speed=0.5)),
    ],
)
def test_movers_never_overlap_another_obstacle(preset, cond):
    from lerobot_formation.bench.scene_sets import parse_scenes

    scenes = parse_scenes(f"{preset}:40", 1_000_000)
    moving = np.linalg.norm(obstacle_velocities(scenes, cond), axis=-1) > 0
    assert moving.sum() >= 40  # the test sees many movers
    rec = rollout(scenes, Straight(0.0), max_steps=200, conditions=cond)  # 20 s: hundreds of meetings
    gaps = _mover_gaps(rec, scenes, moving)
    assert gaps.size > 0 and gaps.min() >= -1e-9
    # and they do meet obstacles: some come within one step of another and turn there
    assert (gaps < cond.obstacle_speed * 0.1 + 1e-9).any()


def test_a_mover_bounces_off_a_static_obstacle_and_off_another_mover():
    # a mover heading straight at a standing obstacle turns back at its surface
    scene = {
        "obstacles": [[3.0, 5.0, 0.5], [6.0, 5.0, 0.5], [3.0, 8.0, 0.4], [6.0, 8.0, 0.4]],
        "goal": [0.0, 14.0],
        "velocities": [[1.0, 0.0], [0.0, 0.0], [1.0, 0.0], [-1.0, 0.0]],
    }
    scenes = scenes_from_list([scene])
    rec = rollout(scenes, Straight(0.0), max_steps=60)
    x = rec.obstacle_paths[0, :, 0, 0]
    assert x.max() <= 5.0 + 1e-9 and x[-1] < x.max() - 1.0  # stopped at the surface, then went back
    np.testing.assert_array_equal(rec.obstacle_paths[0, :, 1], np.tile([6.0, 5.0], (61, 1)))
    # two movers closing head on part again, never overlapping
    gap = np.linalg.norm(rec.obstacle_paths[0, :, 2] - rec.obstacle_paths[0, :, 3], axis=-1) - 0.8
    assert gap.min() >= -1e-9 and gap.min() < 0.2 and gap[-1] > 1.0
