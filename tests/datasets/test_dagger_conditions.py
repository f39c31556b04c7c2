"""DAgger branch scenes under realistic conditions (``datasets_scripts.dagger_scenes``)."""

from __future__ import annotations

import numpy as np
import pytest

from datasets_scripts import dagger_scenes
from lerobot_formation.core.controllers.pac import PACController
from lerobot_formation.core.episodes.levels import get_level
from lerobot_formation.core.episodes.rollout import rollout
from lerobot_formation.core.perception.conditions import Conditions
from lerobot_formation.core.world.scene_files import load_scenes, save_scenes, scenes_from_list
from lerobot_formation.core.world.scenes import Scenes


def test_rollout_setting_of_a_level_and_flags():
    preset, cond = dagger_scenes.rollout_setting("level5", None, {"action_delay": 0, "pose_noise": 0.1})
    assert preset == "structures"
    assert cond == Conditions(
        **{**get_level("level5").conditions.changed(), "action_delay": 0, "pose_noise": 0.1}
    )
    assert dagger_scenes.rollout_setting(None, None, {}) == ("wide", Conditions())
    assert dagger_scenes.rollout_setting("0", "paper,gates", {})[0] == "paper,gates"
    with pytest.raises(ValueError, match="unknown level"):
        dagger_scenes.rollout_setting("level9", None, {})
    with pytest.raises(ValueError, match="needs obstacle_speed > 0"):
        dagger_scenes.rollout_setting(None, None, {"moving_obstacles": 1})


def test_branch_scenes_hold_moving_obstacles_where_they_were(tmp_path):
    item = {
        "obstacles": [[2.0, 5.0, 0.5], [-3.0, 6.0, 0.4]],
        "goal": [0.0, 10.0],
        "start": [0.0, 0.0, np.pi / 2],
        "velocities": [[0.0, 0.0], [0.2, 0.0]],
    }
    scenes = scenes_from_list([item])
    rec = rollout(scenes, PACController(), max_steps=20, conditions=Conditions(pose_noise=0.01))
    b, t = np.array([0]), np.array([10])
    obstacles, velocities = dagger_scenes.branch_obstacles(scenes, rec.obstacle_paths, b, t, 0.1)
    np.testing.assert_allclose(obstacles[0, 1], [-3.0 + 0.2 * 1.0, 6.0, 0.4])  # 10 steps of 0.02 m
    np.testing.assert_array_equal(obstacles[0, 0], [2.0, 5.0, 0.5])
    np.testing.assert_allclose(velocities[0], [[0.0, 0.0], [0.2, 0.0]], atol=1e-12)
    static, none = dagger_scenes.branch_obstacles(scenes, None, b, t, 0.1)
    assert none is None and np.array_equal(static, scenes.obstacles)
    branch = Scenes(obstacles, scenes.mask, scenes.goal, rec.poses[b, t], scenes.seeds, velocities)
    save_scenes(branch, tmp_path / "branch.json")
    np.testing.assert_allclose(load_scenes(tmp_path / "branch.json").velocities[0, 1], [0.2, 0.0])
