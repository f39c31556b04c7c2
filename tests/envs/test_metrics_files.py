"""Metrics files (issue 27): a run never mixes silently with an earlier one in
``--env.episode_metrics_path``, and an episode of a scenes file names its scene by its index in the
file, in the JSONL and in the bench's ``results.json``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lerobot_formation.bench.cli import main as bench_main
from lerobot_formation.envs.env_config import FormationEnvConfig

NEAR_GOALS = [{"obstacles": [], "goal": [0.0, 0.5]}, {"obstacles": [], "goal": [0.0, 0.7]}]  # a few steps


def _scenes_file(tmp_path: Path) -> Path:
    path = tmp_path / "scenes.json"
    path.write_text(json.dumps({"scenes": NEAR_GOALS}))
    return path


def _one_run(cfg: FormationEnvConfig, seeds: list[int]) -> None:
    vec = cfg.create_envs(len(seeds))["formation"][0]
    try:
        vec.reset(seed=seeds[0], options={"lerobot_new_rollout": True})
        for _ in range(15):
            vec.step(np.tile([0.6, 0.0], (len(seeds), 1)).astype(np.float32))
    finally:
        vec.close()


def test_an_earlier_runs_file_is_refused_naming_it(tmp_path):
    log = tmp_path / "metrics.jsonl"
    log.write_text('{"run_id": "an earlier run"}\n')
    with pytest.raises(ValueError) as e:
        FormationEnvConfig(episode_metrics_path=str(log))
    assert str(log) in str(e.value) and "1 lines" in str(e.value)
    assert "--env.episode_metrics_exists=append" in str(e.value) and "=overwrite" in str(e.value)
    with pytest.raises(ValueError, match="episode_metrics_exists must be one of .* got 'keep'"):
        FormationEnvConfig(episode_metrics_path=str(tmp_path / "new.jsonl"), episode_metrics_exists="keep")
    assert log.read_text() == '{"run_id": "an earlier run"}\n'  # untouched


@pytest.mark.parametrize("mode", ["append", "overwrite"])
def test_append_and_overwrite_are_explicit(tmp_path, mode):
    log = tmp_path / "metrics.jsonl"
    log.write_text('{"run_id": "an earlier run"}\n')
    cfg = FormationEnvConfig(
        scenes_file=str(_scenes_file(tmp_path)),
        episode_length=15,
        episode_metrics_path=str(log),
        episode_metrics_exists=mode,
    )
    _one_run(cfg, [0, 1])
    _one_run(cfg, [0, 1])  # a second evaluation of the same process (lerobot-train) appends
    runs = [json.loads(line)["run_id"] for line in log.read_text().splitlines()]
    assert (runs[0] == "an earlier run") == (mode == "append")
    assert len(runs) == 4 + (mode == "append") and len(set(runs)) == 2 + (mode == "append")


def test_a_new_file_then_a_second_run_of_the_same_process(tmp_path):
    log = tmp_path / "sub" / "metrics.jsonl"
    cfg = FormationEnvConfig(
        scenes_file=str(_scenes_file(tmp_path)), episode_length=15, episode_metrics_path=str(log)
    )
    _one_run(cfg, [0, 1])
    _one_run(cfg, [0, 1])
    lines = [json.loads(line) for line in log.read_text().splitlines()]
    assert len(lines) == 4
    # The scenes of a file have no seed: each line names its scene by its index in the file.
    assert sorted((ln["scene_index"], ln["scene_seed"]) for ln in lines) == [(0, None)] * 2 + [(1, None)] * 2


def test_sampled_scenes_have_a_seed_and_no_index(tmp_path):
    log = tmp_path / "metrics.jsonl"
    cfg = FormationEnvConfig(episode_length=3, episode_metrics_path=str(log))
    _one_run(cfg, [7])
    (line,) = [json.loads(line) for line in log.read_text().splitlines()]
    assert line["scene_seed"] == 7 and line["scene_index"] is None


def test_results_json_episodes_name_file_scenes_by_index(tmp_path):
    out = tmp_path / "out"
    argv = ["--controllers", "pac", "--scenes", str(_scenes_file(tmp_path)), "--out", str(out)]
    assert bench_main(argv + ["--no-figures", "--no-progress"]) == 0
    episodes = json.loads((out / "results.json").read_text())["pac"]["episodes"]
    assert [(e["scene_index"], e["seed"]) for e in episodes] == [(0, None), (1, None)]
    out2 = tmp_path / "out2"
    argv = [
        "--controllers",
        "pac",
        "--scenes",
        "random:2",
        "--out",
        str(out2),
        "--no-figures",
        "--no-progress",
    ]
    assert bench_main(argv) == 0
    episodes = json.loads((out2 / "results.json").read_text())["pac"]["episodes"]
    assert [(e["scene_index"], e["seed"]) for e in episodes] == [(0, 1_000_000), (1, 1_000_001)]


def test_the_vector_env_reports_the_file_index_too(tmp_path):
    from lerobot_formation.envs.vector_env import FormationVectorEnv

    vec = FormationVectorEnv(2, scenes_file=str(_scenes_file(tmp_path)))
    _, info = vec.reset(seed=0)
    assert info["scene_index"].tolist() == [0.0, 1.0] and info["scene_seed"].tolist() == [-1, -1]
    _, info = FormationVectorEnv(2).reset(seed=5)
    assert np.isnan(info["scene_index"]).all() and info["scene_seed"].tolist() == [5, 6]
