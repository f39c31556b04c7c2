"""A formation dataset loads through stock ``LeRobotDataset`` without a traceback on a machine without
FFmpeg, with the documented recipe and without this project imported.

Why a recipe: ``LeRobotDataset(repo_id, root=...)`` asks ``get_safe_default_video_backend()`` for a
video decoder whenever ``video_backend`` is not given. That imports torchcodec, which on a machine
without FFmpeg's shared libraries fails, and LeRobot logs the whole loading traceback (ten of them,
one pair per FFmpeg version tried) before falling back to pyav. Formation datasets hold no video, so
the decoder is never used: ``video_backend="pyav"`` names it and the probe never runs. (Installing
FFmpeg 4-8, e.g. ``apt-get install ffmpeg``, also quiets it.)
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from lerobot_formation.data import lerobot_writer

REPO_ID = "local/quiet_stock_load"
LOAD = """
import sys
from lerobot.datasets.lerobot_dataset import LeRobotDataset
ds = LeRobotDataset({repo_id!r}, root={root!r}{extra})
frame = ds[0]
assert "lerobot_formation" not in sys.modules, "the stock load imported this project"
assert ds.meta.video_keys == [], ds.meta.video_keys
print("frames", len(ds), "torchcodec loaded", "torchcodec" in sys.modules)  # a failed import is not kept
"""


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("quiet") / "formation"
    lerobot_writer.generate(root, REPO_ID, 2, progress=False)
    return root


def _stock_load(root: Path, extra: str, cwd: Path) -> subprocess.CompletedProcess:
    """The stock load in a fresh interpreter, outside the repository (so nothing of it is importable
    by accident), offline."""
    env = {
        **os.environ,
        "HF_HUB_OFFLINE": "1",
        "HF_DATASETS_OFFLINE": "1",
        "HF_LEROBOT_HOME": str(cwd / "hf_lerobot"),
        "OMP_NUM_THREADS": "1",
    }
    env.pop("PYTHONPATH", None)
    code = LOAD.format(repo_id=REPO_ID, root=str(root), extra=extra)
    return subprocess.run(
        [sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=300
    )


def test_the_recipe_loads_a_formation_dataset_without_a_traceback(dataset, tmp_path):
    proc = _stock_load(dataset, ', video_backend="pyav"', tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.startswith("frames ") and int(proc.stdout.split()[1]) > 0
    output = proc.stdout + proc.stderr
    assert "Traceback" not in output and "torchcodec" not in proc.stderr, proc.stderr[-3000:]


@pytest.mark.slow  # documents the problem; the fast tier checks the fix
def test_without_the_recipe_a_machine_without_ffmpeg_prints_the_tracebacks(dataset, tmp_path):
    """What the recipe avoids (checked only where torchcodec cannot load FFmpeg)."""
    proc = _stock_load(dataset, "", tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    if proc.stdout.split()[-1] == "True":
        pytest.skip("this machine has FFmpeg's libraries: torchcodec loads and nothing is printed")
    assert "Traceback" in proc.stderr and "'torchcodec' is installed but cannot be loaded" in proc.stderr
