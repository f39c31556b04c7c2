"""scripts/collision_report.py: what it says of a collision, on a team driven straight into an obstacle."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from lerobot_formation.core.dynamics import FormationParams
from lerobot_formation.core.rollout import COLLISION, rollout
from lerobot_formation.core.scene import Scenes

ROOT = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location(
        "collision_report", ROOT / "scripts" / "collision_report.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class _Straight:
    name = "straight"

    def reset(self, view):
        pass

    def act(self, view, idx):
        return np.tile([[0.4, 0.0]], (len(idx), 1))


def test_a_team_driven_into_an_obstacle_is_reported_by_its_leader():
    params = FormationParams()
    scenes = Scenes(
        obstacles=np.array([[[0.5, 3.0, 0.3], [-4.0, 9.0, 0.5]]]),
        mask=np.ones((1, 2), bool),
        goal=np.array([[0.0, 12.0]]),
        start=np.array([[0.0, 0.0, np.pi / 2]]),
        seeds=np.array([-1]),
    )
    rec = rollout(scenes, _Straight(), params, max_steps=200)
    assert rec.outcome[0] == COLLISION
    lines, dwelt = _script().collision_lines(rec, scenes, params)
    assert len(lines) == 1 and dwelt == 0  # at 0.4 m/s, never close before
    assert "agent 1 " in lines[0] and "speed 0.40 m/s" in lines[0] and "obstacle rank 0" in lines[0]


def test_a_bad_level_names_the_value():
    with pytest.raises(ValueError, match="level9"):
        _script().main(["--policy.path", "nowhere", "--level", "level9"])
