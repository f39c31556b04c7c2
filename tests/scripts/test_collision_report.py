"""scripts/collision_report.py: what it says of a collision, on a team driven straight into an obstacle."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from lerobot_formation.core.episodes.rollout import COLLISION, rollout
from lerobot_formation.core.perception.conditions import Conditions
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.core.world.scenes import Scenes

ROOT = Path(__file__).resolve().parents[2]


def _script():
    spec = importlib.util.spec_from_file_location(
        "collision_report", ROOT / "scripts" / "collision_report.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _scene(obstacle, velocity=None) -> Scenes:
    """One scene: a team at the origin facing +y, the goal 12 m ahead, ``obstacle`` [x, y, r] and a
    far one; ``velocity`` [vx, vy] moves the first."""
    velocities = None if velocity is None else np.array([[velocity, [0.0, 0.0]]])
    return Scenes(
        obstacles=np.array([[obstacle, [-4.0, 9.0, 0.5]]]),
        mask=np.ones((1, 2), bool),
        goal=np.array([[0.0, 12.0]]),
        start=np.array([[0.0, 0.0, np.pi / 2]]),
        seeds=np.array([-1]),
        velocities=velocities,
    )


class _Straight:
    name = "straight"

    def reset(self, view):
        pass

    def act(self, view, idx):
        return np.tile([[0.4, 0.0]], (len(idx), 1))


class _DriveThenStand(_Straight):
    """Out of the start zone (movers bounce off it), then still."""

    def act(self, view, idx):
        self.t = getattr(self, "t", 0) + 1
        return np.tile([[0.4 if self.t <= 40 else 0.0, 0.0]], (len(idx), 1))


def test_a_team_driven_into_an_obstacle_is_reported_by_its_leader():
    params = FormationParams()
    scenes = _scene([0.5, 3.0, 0.3])
    rec = rollout(scenes, _Straight(), params, max_steps=200)
    assert rec.outcome[0] == COLLISION
    lines, dwelt, movers, struck = _script().collision_lines(rec, scenes, params)
    assert len(lines) == 1 and dwelt == 0 and movers == 0 and struck == 0  # at 0.4 m/s, never close before
    assert "agent 1 " in lines[0] and "speed 0.40 m/s" in lines[0] and "obstacle rank 0" in lines[0]
    assert "mover" not in lines[0]


def test_a_mover_that_runs_into_a_standing_team_is_named():
    params = FormationParams()
    scenes = _scene([3.0, 1.9, 0.3], velocity=[-0.3, 0.0])

    moving = Conditions(moving_obstacles=1, obstacle_speed=0.3)
    rec = rollout(scenes, _DriveThenStand(), params, max_steps=200, conditions=moving)
    assert rec.outcome[0] == COLLISION
    lines, _, movers, struck = _script().collision_lines(rec, scenes, params)
    assert (
        movers == 1 and "speed 0.00 m/s" in lines[0] and "a mover at 0.30 m/s (+0.19 towards it)" in lines[0]
    )
    assert lines[0].endswith("struck: the team was not closing on it") and struck == 1
    # with a sensing range: how long before the contact some agent first came within it of the mover
    # (the controller ignores what it sees, so every range gives the same episode)
    t = int(rec.steps[0])

    def sensed(r):
        ranged = Conditions(moving_obstacles=1, obstacle_speed=0.3, sensing_range=r, obstacle_memory=True)
        rec_r = rollout(scenes, _DriveThenStand(), params, max_steps=200, conditions=ranged)
        assert rec_r.outcome[0] == COLLISION and int(rec_r.steps[0]) == t
        line = _script().collision_lines(rec_r, scenes, params, sensed=True)[0][0]
        return float(line.split(", sensed ")[1].split(" s before")[0])

    assert sensed(3.0) == round(t * params.dt, 1)  # 2.84 m from the right leader at the start

    # from 0.5 m of an agent's centre to contact (0.1 m, its radius) a 0.3 m/s mover needs >= 1.33 s
    assert t * params.dt > sensed(1.0) > sensed(0.5) >= 0.4 / 0.3 - 0.05
    assert "sensed" not in lines[0]


def test_a_bad_level_names_the_value(capsys):
    with pytest.raises(SystemExit):
        _script().main(["--policy.path", "nowhere", "--level", "level9"])
    assert "level9" in capsys.readouterr().err


def test_a_diffusion_controller_without_a_checkpoint_is_refused(capsys):
    with pytest.raises(SystemExit):
        _script().main(["--level", "level0"])
    assert "needs a policy path" in capsys.readouterr().err


def test_summary_line_gives_outcomes_and_the_successes_motion(capsys):
    """The last line: success, collisions, timeouts, and jerk and smoothness over the successes (none
    in 30 steps, which it says)."""
    assert (
        _script().main(["--controller", "pac", "--level", "level0", "--scenes", "2", "--max-steps", "30"])
        == 0
    )
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith(
        "pac on level0 (2 scenes from seed 5000000): success 0.0 %, collisions 0, timeouts 2"
    )
    assert last.endswith("no successful episode")


def test_the_trace_follows_a_mover_into_a_standing_team():
    """The trace of the mover test's episode: one line a step of the last ``steps``, the mover named
    with its gap, where it is in the team's frame (ahead, to the right) and how fast it comes, and
    the gap below zero at the end."""
    params = FormationParams()
    scenes = _scene([3.0, 1.9, 0.3], velocity=[-0.3, 0.0])

    moving = Conditions(moving_obstacles=1, obstacle_speed=0.3)
    rec = rollout(scenes, _DriveThenStand(), params, max_steps=200, conditions=moving)
    n = int(rec.steps[0])
    lines = _script().trace_lines(rec, scenes, params, 0, steps=5)
    assert (
        len(lines) == 6
        and lines[0].startswith(f"step {n - 5:4d} pose")
        and lines[-1].startswith(f"step {n:4d}")
    )
    assert "sent (0.00, +0.00) ran (0.00, +0.00)" in lines[0] and "sent" not in lines[-1]  # the end frame
    assert "mover 0: gap" in lines[0] and "m right, 0.30 m/s" in lines[0] and "towards agent 1" in lines[0]
    assert "gap -" in lines[-1].split(" | ")[1]  # the collision frame
    assert " | replan" not in lines[0]  # no recorder: no layer column


def test_a_trace_of_an_episode_not_in_the_run_is_refused(capsys):
    with pytest.raises(SystemExit):
        _script().main(["--controller", "pac", "--level", "level0", "--scenes", "2", "--trace", "2"])
    assert "--trace takes episodes 0 .. 1 of this run, got [2]" in capsys.readouterr().err


def test_the_trace_of_the_safety_layer_says_what_each_replan_kept(capsys):
    policy = str(ROOT / "pretrained" / "formation_diffusion_route_v1")
    args = [
        "--policy.path",
        policy,
        "--level",
        "level0",
        "--scenes",
        "2",
        "--max-steps",
        "12",
        "--candidates",
        "3",
    ]
    assert _script().main([*args, "--trace", "1", "--trace-steps", "12", "--threads", "1"]) == 0
    out = capsys.readouterr().out
    lines = out[out.index("episode 1 (timeout after 12 steps):") :].strip().splitlines()[1:-1]
    assert len(lines) == 13 and lines[0].startswith("step    0 pose")
    kept = ("safe, kept a sample", "safe, kept the proposal", "safe, kept a search path")
    assert lines[0].endswith(kept)
    assert "replan: " in lines[0] and " of 4 safe" in lines[0]  # 3 samples and the proposal (no movers)
    assert any(line.endswith("running on") for line in lines)
