"""``lerobot-formation-bench --controllers oracle``: the oracle runs as a registered controller, its
episodes carry why it left a scene, and the artifact keeps the causes (``bench.artifacts``)."""

import json

from lerobot_formation.bench import cli
from lerobot_formation.bench.artifacts import check_artifact, reduce_results
from lerobot_formation.core.episodes.oracle import CAUSES, ORACLE_KEY, SOLVED


def test_the_bench_runs_the_oracle_and_the_artifact_keeps_its_causes(tmp_path):
    out = tmp_path / "out"
    argv = ["--controllers", "oracle", "--scenes", "level0:3", "--threads", "1", "--no-figures"]
    assert cli.main([*argv, "--no-progress", "--out", str(out)]) == 0
    payload = json.loads((out / "results.json").read_text())
    episodes = payload["oracle"]["episodes"]
    assert len(episodes) == 3
    for e in episodes:
        assert (e["outcome"] == "success") == (e[ORACLE_KEY] == SOLVED)
        assert e[ORACLE_KEY] in (SOLVED, *CAUSES) and e["oracle_rounds"] >= 1
    artifact = reduce_results(payload, command="lerobot-formation-bench --controllers oracle")
    check_artifact(artifact)
    oracle = artifact["sets"]["level0"]["controllers"]["oracle"]
    assert oracle["unsolved"] == {
        str(e["scene_index"]): e[ORACLE_KEY] for e in episodes if e[ORACLE_KEY] != SOLVED
    }
