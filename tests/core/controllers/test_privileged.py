"""The privileged expert (``rollout(privileged=True)``, ``ConditionedWorld.privileged``), PAC's
prediction of moving obstacles and delay compensation, randomized conditions and scene mixtures."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import Spy

from lerobot_formation.core.controllers.pac import PACController, PathAwareController, swept_obstacles
from lerobot_formation.core.episodes.rollout import Teams, rollout
from lerobot_formation.core.perception.conditions import Conditions, randomized_conditions
from lerobot_formation.core.world.dynamics import FormationParams, rollout_poses
from lerobot_formation.core.world.presets import STRUCTURE_PRESETS, distribution_slots, scene_preset
from lerobot_formation.core.world.sampling import sample_distribution, sample_mixed, sample_scenes
from lerobot_formation.core.world.scene_files import scenes_from_list
from lerobot_formation.core.world.scenes import FAR

# One obstacle right of the straight line, 5 m ahead: far beyond a 1 m sensing range at the start.
BESIDE = {"obstacles": [[2.0, 5.0, 0.5]], "goal": [0.0, 10.0], "start": [0.0, 0.0, np.pi / 2]}


def test_privileged_expert_sees_what_the_recorded_observation_does_not():
    scenes = scenes_from_list([BESIDE])
    cond = Conditions(sensing_range=1.0, pose_noise=0.05)
    spy = Spy(PACController())
    rec = rollout(
        scenes, spy, max_steps=5, conditions=cond, record_observations=("nearest", None), privileged=True
    )
    assert (rec.seen_step == -1).all()  # never sensed in these 5 steps
    for t, view in enumerate(spy.views[1:]):
        assert view.mask[0, 0] and view.map_version[0] == 0
        np.testing.assert_array_equal(view.obstacles[0, 0], [2.0, 5.0, 0.5])
        np.testing.assert_array_equal(view.pose, rec.poses[:, t])  # the true pose, no noise
    # the recorded frames are what the team perceived: a noisy pose, and in the 'nearest' encoding
    # (goal, then [bx, by, r, present] per slot) no obstacle at all, where a perceiving team with the
    # obstacle in range would have one
    assert not np.allclose(rec.observations["agent_pos"][0, 0, :2], scenes.start[0, :2])
    assert not rec.observations["environment_state"][0, : rec.steps[0] + 1, 2:].any()
    near = rollout(
        scenes,
        PACController(),
        max_steps=1,
        conditions=Conditions(sensing_range=9.0),
        record_observations=("nearest", None),
    )
    assert near.observations["environment_state"][0, 0, 2:].any()
    perceived = Spy(PACController())
    rollout(scenes, perceived, max_steps=5, conditions=cond)
    assert not any(v.mask.any() for v in perceived.views)  # the perceiving controller never sees it


def test_privileged_map_keeps_moving_obstacles_off():
    item = {
        **BESIDE,
        "obstacles": [[2.0, 5.0, 0.5], [-2.0, 5.0, 0.4]],
        "velocities": [[0.0, 0.0], [0.3, 0.0]],
    }
    teams = Teams(scenes_from_list([item]), conditions=Conditions(sensing_range=1.0))
    for _ in range(3):
        truth = teams.truth()
        np.testing.assert_array_equal(truth.obstacles[0], teams.scenes.obstacles[0])
        np.testing.assert_array_equal(truth.obstacle_velocity[0, 1], [0.3, 0.0])
        np.testing.assert_array_equal(truth.map_obstacles[0, 0], [2.0, 5.0, 0.5])
        np.testing.assert_array_equal(truth.map_obstacles[0, 1], [FAR, FAR, 0.0])
        assert truth.map_version[0] == 0 and truth.mask[0].all()
        teams.step(np.array([[0.5, 0.0]]))
    assert teams.scenes.obstacles[0, 1, 0] > -2.0  # it moved, and the truth followed it


def test_privileged_without_conditions_changes_nothing():
    scenes = sample_scenes([1_000_000, 1_000_001])
    a = rollout(scenes, PACController(), max_steps=60)
    b = rollout(scenes, PACController(), max_steps=60, privileged=True)
    np.testing.assert_array_equal(a.poses, b.poses)


def test_swept_obstacles_cover_the_path_ahead():
    obs = np.array([[[0.0, 0.0, 0.5], [5.0, 5.0, 1.0], [FAR, FAR, 0.0]]])
    vel = np.array([[[1.0, 0.0], [0.0, 0.0], [0.0, 0.0]]])
    out = swept_obstacles(obs, vel, lead=0.1, lookahead=1.0, spacing=0.25)
    assert out.shape == (1, 3 + 4, 3)
    np.testing.assert_allclose(out[0, 0], [0.1, 0.0, 0.5])  # moved by the lead
    np.testing.assert_array_equal(out[0, 1:3], obs[0, 1:3])  # static and padding stay
    np.testing.assert_allclose(out[0, 3:, 0], [0.35, 0.6, 0.85, 1.1])
    np.testing.assert_array_equal(out[0, 3:, 2], 0.5)
    assert swept_obstacles(obs, np.zeros_like(vel), 0.1, 1.0) is obs


def test_governor_checks_a_mover_where_it_will_be():
    """A stopped team is safe from an obstacle 2 m to its right, unless it comes at 2 m/s."""
    pac = PathAwareController()
    pac.obstacles = np.array([[[2.0, 0.0, 0.3]]])
    pose = np.array([[0.0, 0.0, np.pi / 2]])
    stop = np.zeros((1, 1, 2))
    assert pac.footprint_clearance(pose, stop)[0, 0] > 0.5
    coming = np.array([[[-2.0, 0.0]]])
    assert pac.footprint_clearance(pose, stop, coming)[0, 0] < 0
    leaving = -coming
    assert pac.footprint_clearance(pose, stop, leaving)[0, 0] > 0.5


def test_delay_compensation_acts_for_the_pose_after_the_queued_commands():
    scenes = sample_scenes([1_000_003])
    teams = Teams(scenes, conditions=Conditions(action_delay=1))
    view = teams.truth()
    late, plain = PACController(delay=1), PACController()
    late.reset(view)
    plain.reset(view)
    first = late.act(view, np.arange(1))
    np.testing.assert_array_equal(first, plain.act(view, np.arange(1)))  # nothing queued yet
    second = late.act(view, np.arange(1))
    ahead = view[np.arange(1)]
    ahead.pose = rollout_poses(view.pose, first[:, None, None], FormationParams().dt)[:, 0, -1]
    np.testing.assert_array_equal(second, plain.act(ahead, np.arange(1)))
    with pytest.raises(ValueError, match="delay must be an integer number of steps >= 0, got -1"):
        PACController(delay=-1)


def test_randomized_conditions_repeat_per_key_vary_across_keys_and_stay_under_the_ceiling():
    ceiling = Conditions(
        sensing_range=3.0,
        obstacle_noise=0.05,
        pose_noise=0.05,
        action_noise=0.05,
        action_delay=2,
        max_linear_accel=0.5,
        max_angular_accel=2.0,
        moving_obstacles=2,
        obstacle_speed=0.3,
    )
    draws = [randomized_conditions(ceiling, k) for k in range(60)]
    assert draws == [randomized_conditions(ceiling, k) for k in range(60)]
    assert len(set(draws)) == 60
    on = np.array(
        [
            [
                getattr(d, f) not in (None, 0, 0.0)
                for f in ("sensing_range", "pose_noise", "action_delay", "moving_obstacles")
            ]
            for d in draws
        ]
    )
    assert 0.4 < on.mean() < 0.8  # each on with probability 0.6
    for d in draws:
        assert d.sensing_range is None or 3.0 <= d.sensing_range <= 6.0
        assert d.obstacle_noise <= 0.05 and d.pose_noise <= 0.05 and d.action_noise <= 0.05
        assert d.action_delay in (0, 1, 2) and d.moving_obstacles in (0, 1, 2)
        assert d.moving_obstacles == 0 or 0.15 <= d.obstacle_speed <= 0.3
        assert (d.max_linear_accel is None) == (d.max_angular_accel is None)
    assert {d.action_delay for d in draws} == {0, 1, 2} and {d.moving_obstacles for d in draws} == {0, 1, 2}
    with pytest.raises(ValueError, match="p_on must be in"):
        randomized_conditions(ceiling, 0, p_on=1.5)


def test_scene_distributions_mixtures_and_lists():
    seeds = np.arange(100, 110)
    mixed = sample_distribution(seeds, "structures")
    np.testing.assert_array_equal(mixed.obstacles, sample_mixed(seeds, STRUCTURE_PRESETS).obstacles)
    np.testing.assert_array_equal(
        sample_distribution(seeds[:3], "wide").obstacles,
        sample_scenes(seeds[:3], scene_preset("wide")).obstacles,
    )
    both = sample_distribution(seeds, "paper,structures")
    np.testing.assert_array_equal(both[[0]].goal, sample_scenes(seeds[:1]).goal)  # seed 100: entry 0
    # seed 101 is entry 1, structures' preset (101 // 2) % 5 = 0: bend
    np.testing.assert_array_equal(both[[1]].start, sample_scenes([101], scene_preset("bend")).start)
    assert both.obstacles.shape[1] == distribution_slots("paper,structures")
    with pytest.raises(ValueError, match="'nope' of 'paper,nope' is neither a preset"):
        sample_distribution(seeds, "paper,nope")
