"""The benchmark scripts bench_demo_time.py and bench_sampling_steps.py: their --help (fast, in a
subprocess as a user runs them) and bench_sampling_steps' pure helpers. Nothing here runs a benchmark."""

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _script(relpath: str):
    path = REPO / relpath
    spec = importlib.util.spec_from_file_location(f"_bench_test_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize(
    ("script", "flags"),
    [
        (
            "benchmarks/bench_demo_time.py",
            ["--quick", "--threads N", "--load", "--via-run-sh", "-- DEMO ARGS"],
        ),
        (
            "benchmarks/bench_sampling_steps.py",
            ["--quick", "--threads N", "--steps", "--scenes", "--controller", "--inference-backend", "--out"],
        ),
    ],
)
def test_help(script, flags):
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(
        [sys.executable, str(REPO / script), "--help"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    for flag in flags:
        assert flag in proc.stdout, f"{script} --help lacks {flag!r}:\n{proc.stdout}"


def test_sampling_steps_helpers():
    m = _script("benchmarks/bench_sampling_steps.py")
    assert m.int_list("10, 1,2,2") == [10, 1, 2]
    with pytest.raises(Exception, match="steps must be >= 1"):
        m.int_list("0")
    assert m.overlaps((0.1, 0.5), (0.5, 0.9)) and not m.overlaps((0.1, 0.4), (0.5, 0.9))
    res = {
        1: {"a": {"success_ci95": [0.0, 0.2]}, "b": {"success_ci95": [0.5, 0.8]}},
        3: {"a": {"success_ci95": [0.3, 0.6]}, "b": {"success_ci95": [0.4, 0.7]}},
        10: {"a": {"success_ci95": [0.4, 0.7]}, "b": {"success_ci95": [0.5, 0.8]}},
    }
    assert m.within_noise(res, 10) == [3, 10]  # 1 overlaps on "b" only: not within noise
    sets = {"a": {"wall_s": 2.0, "replans": 10}, "b": {"wall_s": 1.0, "replans": 20}}
    assert m.seconds_per_replan(sets) == pytest.approx(0.1)
    assert m.seconds_per_replan({"a": {"wall_s": 1.0, "replans": None}}) is None
