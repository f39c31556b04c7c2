"""scripts/jerk_sources.py: jerk put in the class of the event next to it (the recorder: test_level_report.py)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
DT = 0.1


def _script():
    spec = importlib.util.spec_from_file_location("jerk_sources", ROOT / "scripts" / "jerk_sources.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _straight_with_a_step(step: int, n: int = 30) -> np.ndarray:
    """(1, n + 1, 2) positions along y: 0.3 m/s, then 0.5 m/s from command ``step`` on."""
    speed = np.where(np.arange(n) < step, 0.3, 0.5)
    y = np.concatenate([[0.0], np.cumsum(speed * DT)])
    return np.stack([np.zeros_like(y), y], axis=-1)[None]


def _events(n: int, **at: int) -> dict[str, np.ndarray]:
    module = _script()
    events = {name: np.zeros((1, n), bool) for name in module.EVENTS}
    for name, step in at.items():
        events[name][0, step] = True
    return events


def test_a_speed_step_is_put_in_the_class_of_the_replan_that_made_it():
    module = _script()
    positions, steps = _straight_with_a_step(10), np.array([30])
    count, total = module.jerk_sources(positions, steps, _events(30, proposal=10), DT)
    assert count["proposal"] == 2  # the jerk at t = 8 and 9 reads command 10
    assert sum(count.values()) == 28  # 31 positions: 28 third differences
    np.testing.assert_allclose(total["proposal"], 2 * 0.2 / DT**2)  # |dv| / dt^2 at both
    assert total["none"] < 1e-9  # constant speed elsewhere
    # a filter change at the same step takes precedence over the replan's class
    count, total = module.jerk_sources(positions, steps, _events(30, proposal=10, filter=10), DT)
    assert count["filter"] == 2 and count["proposal"] == 0
    # an event far from the step leaves its jerk in "none"
    count, total = module.jerk_sources(positions, steps, _events(30, escape=20), DT)
    np.testing.assert_allclose(total["none"], 2 * 0.2 / DT**2)
    assert count["escape"] == 2 and total["escape"] < 1e-9


def test_the_report_prints_one_line_per_class_and_the_summary(capsys):
    module = _script()
    policy = str(ROOT / "pretrained" / "formation_diffusion_route_v1")
    args = ["--policy.path", policy, "--level", "level0", "--scenes", "2", "--max-steps", "40"]
    assert module.main([*args, "--candidates", "3", "--chunk-smoothing", "0", "--threads", "1"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()[-7:]  # after the loader's own line
    assert [line.split(" ")[0] for line in lines[:6]] == [
        "filter",
        "escape",
        "proposal",
        "replan",
        "replan",
        "none",
    ]
    assert lines[-1].startswith("diffusion-safe on level0 (2 scenes from seed 5000000): success 0.0 %")
    assert lines[-1].endswith("no successful episode")  # 4 s is too short to arrive
