"""A sharded run of a diffusion controller merges to the whole run (issue 61, item 7).

``diffusion-safe`` with the shipped checkpoint on 30 level5 tuning scenes, once whole and as shards
0/3, 1/3 and 2/3 merged by ``lerobot-formation-bench-merge``: every episode ends the same (outcome and
step) and its metrics agree. Each episode draws its sampler's noise from its own stream and is sampled
in a denoiser call of its own (``policy.replanner.Replanner.act``), so the two runs are equal bit for
bit; the tolerance (relative 1e-9) leaves room only for the metrics' own arithmetic. Before, with one
noise stream per run and batched denoiser calls, 1 of these 30 episodes ended otherwise (a collision
against a timeout) and most others moved by up to a few metres: the ~1e-6 rounding of a batched
U-Net grows over an episode into another choice of the safety layer.
"""

import json
from pathlib import Path

import numpy as np
import pytest

from lerobot_formation.bench.cli import main as bench_main
from lerobot_formation.bench.merge import main as merge_main
from lerobot_formation.core.episodes.levels import TUNING_SEED_START

CHECKPOINT = Path(__file__).resolve().parents[2] / "pretrained" / "formation_diffusion_route_v1"
CONTROLLER, SCENES, SHARDS = "diffusion-safe", "level5:30", 3
RTOL = 1e-9


def _bench(out: Path, *extra: str) -> None:
    argv = ["--controllers", CONTROLLER, "--policy.path", str(CHECKPOINT), "--scenes", SCENES]
    argv += ["--seed", str(TUNING_SEED_START), "--threads", "1", "--no-figures", "--no-progress"]
    assert bench_main([*argv, "--out", str(out), *extra]) == 0


def _episodes(folder: Path) -> list[dict]:
    payload = json.loads((folder / "results.json").read_text())
    return payload["by_scenes"]["level5"][CONTROLLER]["episodes"]


@pytest.mark.slow
def test_three_merged_shards_of_diffusion_safe_are_the_whole_run(tmp_path, capsys):
    if not CHECKPOINT.is_dir():
        pytest.skip("no shipped checkpoint")
    _bench(tmp_path / "whole")
    for i in range(SHARDS):
        _bench(tmp_path / f"s{i}", "--shard", f"{i}/{SHARDS}")
    shards = [str(tmp_path / f"s{i}") for i in range(SHARDS)]
    assert merge_main([*shards, "--out", str(tmp_path / "merged")]) == 0
    whole, merged = _episodes(tmp_path / "whole"), _episodes(tmp_path / "merged")
    assert [e["scene_index"] for e in merged] == list(range(30))
    ends = [(e["outcome"], e["steps"]) for e in whole]
    assert [(e["outcome"], e["steps"]) for e in merged] == ends
    assert len({o for o, _ in ends}) > 1, "every episode ended alike: the check would be weak"
    for w, m in zip(whole, merged, strict=True):
        assert w.keys() == m.keys()
        for key, value in w.items():
            if isinstance(value, float):
                got = m[key]
                assert got is not None and np.isclose(got, value, rtol=RTOL, atol=0.0), (
                    f"scene {w['scene_index']}: {key} {value!r} whole, {got!r} merged"
                )
            else:
                assert m[key] == value, f"scene {w['scene_index']}: {key}"
