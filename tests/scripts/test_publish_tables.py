"""scripts/publish_tables.py: the published tables come from the artifacts in results/ (issue 62).

A real tiny bench run (PAC and route pursuit on 3 scenes, one thread) is reduced into an artifact; the
script writes a table from it, ``--check`` passes, and fails when one published number is changed or
a table does not parse. The repository's own README.md and docs/ are checked against results/ too, so
CI fails when they disagree.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from lerobot_formation.bench.artifacts import check_artifact, reduce_results

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
_spec = importlib.util.spec_from_file_location("publish_tables", REPO / "scripts" / "publish_tables.py")
publish_tables = sys.modules["publish_tables"] = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(publish_tables)

SPEC = """
[tables.tiny]
label = "controller"
rows = [{ controller = "pac", label = "PAC" }, { controller = "route-pursuit", label = "route pursuit" }]
columns = [
    { header = "random:3", artifact = "tiny", value = "success" },
    { header = "collisions / timeouts", artifact = "tiny", value = "outcomes" },
    { header = "jerk", artifact = "tiny", value = "jerk" },
    { header = "episodes", artifact = "tiny", value = "n" },
]

[tables.two]
rows_from = "tiny"
columns = [
    { header = "first", artifact = "tiny", value = "success" },
    { header = "second", artifact = "later", value = "success" },
]
"""
COMMAND = ["--controllers", "pac,route-pursuit", "--scenes", "random:3", "--threads", "1", "--no-figures"]


@pytest.fixture(scope="module")
def bench_run(tmp_path_factory) -> Path:
    """A real bench run's output folder (results.json), the command line of the README's tiny example."""
    out = tmp_path_factory.mktemp("bench") / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HF_HUB_OFFLINE": "1"}
    proc = subprocess.run(
        [str(BIN / "lerobot-formation-bench"), *COMMAND, "--no-progress", "--out", str(out)],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


def _root(tmp_path: Path, readme: str = "# x\n\n<!-- table:tiny -->\n<!-- /table:tiny -->\n") -> Path:
    (tmp_path / "results").mkdir()
    (tmp_path / "docs").mkdir()
    (tmp_path / "results" / "tables.toml").write_text(SPEC)
    (tmp_path / "README.md").write_text(readme)
    (tmp_path / "docs" / "page.md").write_text("# page\n\n<!-- table:two -->\n<!-- /table:two -->\n")
    return tmp_path


def _run(root: Path, *args: str, capsys) -> tuple[int, str, str]:
    code = publish_tables.main([*args, "--root", str(root)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_the_artifact_holds_the_runs_counts_command_date_and_host(bench_run):
    payload = json.loads((bench_run / "results.json").read_text())
    artifact = reduce_results(payload)
    check_artifact(artifact)
    assert artifact["command"].startswith("lerobot-formation-bench --controllers pac,route-pursuit")
    assert artifact["date"] == payload["meta"]["date"] and "cores" in artifact["host"]
    pac = artifact["sets"]["random"]["controllers"]["pac"]
    assert pac["n"] == 3 and pac["successes"] == round(payload["pac"]["success_rate"] * 3)
    assert len(pac["outcomes"]) == 3 and pac["jerk"] == payload["pac"]["jerk"]["mean"]
    assert artifact["sets"]["random"]["spec"] == "random:3"
    for broken, message in (
        ({**payload, "meta": {**payload["meta"], "incomplete": True}}, "incomplete"),
        ({**payload, "meta": {**payload["meta"], "shard": "0/2"}}, "merge the shards"),
        ({**payload, "meta": {**payload["meta"], "command": None}}, "no command line"),
    ):
        with pytest.raises(ValueError, match=message):
            reduce_results(broken)
    assert (
        reduce_results({**payload, "meta": {**payload["meta"], "command": None}}, command="x")["command"]
        == "x"
    )


def test_the_script_writes_a_table_and_check_passes(bench_run, tmp_path, capsys):
    root = _root(tmp_path)
    assert _run(root, "--check", capsys=capsys)[0] == 0  # no artifact yet: the tables are pending, empty
    code, out, err = _run(root, "--add", "tiny", str(bench_run), capsys=capsys)
    assert code == 0, err
    payload = json.loads((bench_run / "results.json").read_text())
    readme = (root / "README.md").read_text()
    pac = payload["pac"]
    assert f"| PAC | {publish_tables.percent_interval(round(pac['success_rate'] * 3), 3)} |" in readme
    assert f"{pac['collisions']} / {pac['timeouts']} | {pac['jerk']['mean']:.3g} | 3 |" in readme
    assert f"Measured on {payload['meta']['date']} on " in readme and "`results/tiny.json`" in readme
    page = (root / "docs" / "page.md").read_text()  # one artifact of two: the other's cells are pending
    assert "| PAC | " in page and " | - |" in page and "Pending (no artifact yet): later." in page
    code, out, err = _run(root, "--check", capsys=capsys)
    assert code == 0, err
    assert "table two: pending, no results/later.json" in out
    artifact = json.loads((root / "results" / "tiny.json").read_text())  # a run with its network on a GPU
    (root / "results" / "tiny.json").write_text(json.dumps({**artifact, "device": "cuda"}))
    assert _run(root, capsys=capsys)[0] == 0
    assert ", the network on cuda: `results/tiny.json`" in (root / "README.md").read_text()


def test_check_fails_when_one_published_number_changes(bench_run, tmp_path, capsys):
    root = _root(tmp_path)
    assert _run(root, "--add", "tiny", str(bench_run), capsys=capsys)[0] == 0
    readme = (root / "README.md").read_text()
    line = next(line for line in readme.splitlines() if line.startswith("| route pursuit |"))
    changed = line.replace(" | 3 |", " | 4 |")
    assert changed != line
    (root / "README.md").write_text(readme.replace(line, changed))
    code, _, err = _run(root, "--check", capsys=capsys)
    assert code == 1
    number = readme.splitlines().index(line) + 1
    assert f"README.md:{number}: table tiny: published {changed!r}, the artifacts give {line!r}" in err
    assert _run(root, capsys=capsys)[0] == 0  # publishing writes it back
    assert (root / "README.md").read_text() == readme
    # an artifact whose counts changed gives another table too
    artifact = json.loads((root / "results" / "tiny.json").read_text())
    artifact["sets"]["random"]["controllers"]["pac"].update(successes=2, timeouts=1, outcomes="sst")
    (root / "results" / "tiny.json").write_text(json.dumps(artifact))
    code, _, err = _run(root, "--check", capsys=capsys)
    assert code == 1 and "table tiny" in err and "66.7 [" in err


def test_a_table_that_does_not_parse_fails_the_check(tmp_path, capsys):
    root = _root(tmp_path)
    broken = "# b\n\n| a | b | c |\n|---|---|---|---|\n| 1 | 2 | 3 |\n\n```text\n| not | a table\n```\n"
    (root / "docs" / "broken.md").write_text(broken)
    code, _, err = _run(root, "--check", capsys=capsys)
    assert code == 1 and "docs/broken.md:4: a table row has 4 cells, its header 3" in err
    (root / "docs" / "broken.md").write_text("| a | b |\n| 1 | 2 |\n")
    code, _, err = _run(root, "--check", capsys=capsys)
    assert code == 1 and "docs/broken.md:2: a table without a delimiter row" in err
    (root / "docs" / "broken.md").write_text("| a | `b \\| c` |\n|:---|--:|\n| 1 | 2 |\n")  # an escaped pipe
    assert _run(root, "--check", capsys=capsys)[0] == 0


def test_bad_markers_and_specs_are_one_error_line(tmp_path, capsys):
    root = _root(tmp_path, "<!-- table:tiny -->\nno close marker\n")
    code, _, err = _run(root, "--check", capsys=capsys)
    assert code == 2 and "README.md:1: <!-- table:tiny --> has no <!-- /table:tiny -->" in err
    (root / "README.md").write_text("<!-- table:nosuch -->\n<!-- /table:nosuch -->\n")
    code, _, err = _run(root, "--check", capsys=capsys)
    assert code == 2 and "table 'nosuch' is not in results/tables.toml" in err


def test_rerun_runs_the_recorded_command_again(bench_run, tmp_path, capsys):
    root = _root(tmp_path)
    assert _run(root, "--add", "tiny", str(bench_run), capsys=capsys)[0] == 0
    before = json.loads((root / "results" / "tiny.json").read_text())
    code, out, err = _run(root, "--rerun", "tiny", capsys=capsys)
    assert code == 0, err
    after = json.loads((root / "results" / "tiny.json").read_text())
    assert after["command"] == before["command"]
    assert after["sets"] == before["sets"]  # PAC and route pursuit are deterministic


# --- the repository itself -------------------------------------------------------------------------


def test_the_repositorys_tables_are_what_results_gives():
    """README.md and docs/*.md: every table parses, and every published table is what its artifacts
    in results/ give (a table whose artifacts are not there yet is empty: the next test skips)."""
    proc = subprocess.run(
        [sys.executable, str(REPO / "scripts" / "publish_tables.py"), "--check"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_every_published_table_has_its_artifacts():
    tables = publish_tables.read_spec(REPO / "results" / "tables.toml")
    missing = sorted(
        {a for t in tables.values() for a in t.artifacts() if not (REPO / "results" / f"{a}.json").is_file()}
    )
    if missing:
        pytest.skip(f"results/ holds no artifact yet for {missing}: those tables are published empty")


def _artifact(controllers: dict, spec: str = "level5:4", seed: int = 1_000_000) -> dict:
    def entry(letters, extra=None):
        return {
            "n": len(letters),
            "successes": letters.count("s"),
            "collisions": letters.count("c"),
            "timeouts": letters.count("t"),
            "outcomes": letters,
            **(extra or {}),
        }

    sets = {
        "level5": {"spec": spec, "seed": seed, "controllers": {k: entry(*v) for k, v in controllers.items()}}
    }
    return {
        "format": "lerobot-formation-results",
        "version": 1,
        "command": "lerobot-formation-bench ...",
        "date": "2026-12-07",
        "host": "test",
        "device": "cpu",
        "main": "level5",
        "sets": sets,
    }


def test_the_ceiling_reads_every_runs_solved_scenes(tmp_path, capsys):
    """A ceiling column: the scenes some run solved (the oracle's or any controller's), each controller's
    successes as a share of them, and the causes the oracle gave for the scenes nobody solved; an
    oracle run on other scenes is refused."""
    spec = """
[tables.ceiling]
label = "controller"
rows = [
    { controller = "pac", label = "PAC" },
    { controller = "oracle", label = "oracle" },
    { controller = "*", label = "solvable" },
]
columns = [
    { header = "success", artifact = "lvl", ceiling = "lvl_oracle", value = "success" },
    { header = "of solvable", artifact = "lvl", ceiling = "lvl_oracle", value = "of_solvable" },
    { header = "solvable", artifact = "lvl", ceiling = "lvl_oracle", value = "solvable" },
]

[tables.causes]
rows = [
    { controller = "oracle", label = "oracle", value = "causes" },
    { controller = "oracle", label = "misses", value = "misses" },
]
columns = [{ header = "left", artifact = "lvl", ceiling = "lvl_oracle" }]
"""
    root = tmp_path
    (root / "results").mkdir()
    (root / "results" / "tables.toml").write_text(spec)
    (root / "README.md").write_text(
        "<!-- table:ceiling -->\n<!-- /table:ceiling -->\n\n<!-- table:causes -->\n<!-- /table:causes -->\n"
    )
    # scene 1: PAC only (the oracle's lower bound misses it); scene 3: nobody
    (root / "results" / "lvl.json").write_text(json.dumps(_artifact({"pac": ("sssc",)})))
    unsolved = {"1": "out of time", "3": "struck by a mover"}
    oracle = _artifact({"oracle": ("stsc", {"unsolved": unsolved})})
    (root / "results" / "lvl_oracle.json").write_text(json.dumps(oracle))
    code, out, err = _run(root, capsys=capsys)
    assert code == 0, err
    readme = (root / "README.md").read_text()
    assert "| PAC | 75.0 [" in readme and " | 100.0 | 75.0 [" in readme
    assert "| oracle | 50.0 [" in readme and " | 66.7 | 75.0 [" in readme
    assert "| solvable | 75.0 [" in readme and " | 100.0 | 75.0 [" in readme
    assert "| oracle | 1 struck by a mover |" in readme  # scene 1 was solved by PAC: not a cause ...
    assert "| misses | 1 out of time |" in readme  # ... but the oracle's miss
    oracle["sets"]["level5"]["seed"] = 5_000_000
    (root / "results" / "lvl_oracle.json").write_text(json.dumps(oracle))
    code, out, err = _run(root, capsys=capsys)
    assert code == 2 and "did not run the scenes of" in err
