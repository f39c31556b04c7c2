"""A gym user's first line: importing the package that names the namespace registers the env (as
``import gym_pusht`` does), before or after gymnasium; ``import lerobot_formation`` alone loads
neither gymnasium, torch nor LeRobot. Each case in a fresh interpreter."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
MAKE = (
    "env = gym.make('gym_formation/FormationNav-v0')\n"
    "obs, info = env.reset(seed=0)\n"
    "env.step(env.action_space.sample())\n"
    "print(type(env.unwrapped).__name__, env.spec.max_episode_steps)\n"
)


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
        env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"},
    )


@pytest.mark.parametrize(
    "imports",
    [
        "import gym_formation\nimport gymnasium as gym\n",
        "import gymnasium as gym\nimport gym_formation\n",
        "import lerobot_formation.envs\nimport gymnasium as gym\n",
    ],
    ids=["gym_formation-first", "gymnasium-first", "envs"],
)
def test_import_then_make(imports):
    proc = _run(imports + MAKE)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.split() == ["FormationEnv", "600"]


def test_module_prefix_form_without_any_import():
    """gymnasium imports the module named before ':' itself."""
    proc = _run(
        "import gymnasium as gym\n" + MAKE.replace("'gym_formation/", "'gym_formation:gym_formation/")
    )
    assert proc.returncode == 0, proc.stderr[-3000:]


def test_without_the_import_gymnasium_does_not_find_the_namespace():
    """What gymnasium 1.x does by itself: no namespace auto-import (so the import above is needed)."""
    proc = _run("import gymnasium as gym\n" + MAKE)
    assert proc.returncode != 0 and "Namespace gym_formation not found" in proc.stderr


def test_importing_the_package_loads_nothing_heavy():
    code = (
        "import sys, lerobot_formation, lerobot_formation.core.world.sampling\n"
        "bad = [m for m in ('gymnasium', 'torch', 'lerobot') if m in sys.modules]\n"
        "assert not bad, bad\n"
    )
    proc = _run(code)
    assert proc.returncode == 0, proc.stderr[-3000:]
