"""lerobot-formation-bench's output folder: --out refuses a folder that holds another run unless
--overwrite or --resume; --resume keeps the controllers already finished there; --help in groups
with examples and one line per registered controller."""

from __future__ import annotations

import json

import pytest
from helpers import last_error_line

from lerobot_formation.bench import controllers, results
from lerobot_formation.bench.cli import main
from lerobot_formation.bench.merge import main as merge_main

BASE = ["--scenes", "random:1", "--no-figures", "--no-progress"]  # one scene: these pin the folder


def _run(out, *extra: str) -> int:
    return main([*BASE, "--out", str(out), *extra])


def _results(out) -> dict:
    return json.loads((out / "results.json").read_text())


def test_out_holding_a_run_is_refused_and_the_run_kept(tmp_path, capsys):
    out = tmp_path / "run"
    assert _run(out, "--controllers", "pac") == 0
    before = (out / "results.json").read_bytes()
    with pytest.raises(SystemExit) as e:
        _run(out, "--controllers", "route-pursuit")
    assert e.value.code == 2
    assert last_error_line(capsys.readouterr().err) == (
        f"error: --out {out} already holds a run (results.json); add --overwrite to replace it, "
        "--resume to finish it, or choose another folder"
    )
    assert (out / "results.json").read_bytes() == before


def test_a_folder_with_other_files_but_no_run_is_used(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    assert _run(tmp_path, "--controllers", "pac") == 0
    assert (tmp_path / "notes.txt").read_text() == "mine" and "pac" in _results(tmp_path)


def test_overwrite_replaces_the_run(tmp_path):
    out = tmp_path / "run"
    assert _run(out, "--controllers", "pac") == 0
    assert _run(out, "--controllers", "route-pursuit", "--overwrite") == 0
    res = _results(out)
    assert "route-pursuit" in res and "pac" not in res and res["meta"]["resumed"] == {}
    assert not [p.name for p in out.iterdir() if ".tmp" in p.name]  # written through a renamed temp file


def test_resume_keeps_the_finished_controllers_and_runs_the_rest(tmp_path, capsys):
    out = tmp_path / "run"
    assert _run(out, "--controllers", "pac") == 0
    pac = _results(out)["pac"]
    capsys.readouterr()
    assert _run(out, "--controllers", "pac,route-pursuit", "--resume") == 0
    printed = capsys.readouterr().out
    assert f"resume: kept from {out / 'results.json'}: pac (random)" in printed
    assert "] pac: success" not in printed and "] route-pursuit: success" in printed
    res = _results(out)
    assert res["pac"] == pac  # kept as it was (its wall time too): not run again
    assert res["route-pursuit"]["n_episodes"] == 1
    assert res["meta"]["resumed"] == {"random": ["pac"]} and not res["meta"]["incomplete"]
    # everything finished: nothing runs, nothing is written
    before = (out / "results.json").read_bytes()
    assert _run(out, "--controllers", "route-pursuit,pac", "--resume") == 0
    assert "resume: nothing to run" in capsys.readouterr().out
    assert (out / "results.json").read_bytes() == before


def test_resume_finishes_a_run_that_stopped_on_a_failing_controller(tmp_path, capsys, monkeypatch):
    out = tmp_path / "run"
    real = controllers.CONTROLLER_FACTORIES["route-pursuit"]

    def broken(*args, **kwargs):
        raise ValueError("cannot be made today")

    monkeypatch.setitem(controllers.CONTROLLER_FACTORIES, "route-pursuit", broken)
    with pytest.raises(SystemExit) as e:
        _run(out, "--controllers", "pac,route-pursuit")
    assert e.value.code == 2
    assert last_error_line(capsys.readouterr().err) == "error: controller route-pursuit: cannot be made today"
    stopped = _results(out)
    assert stopped["meta"]["incomplete"] and "route-pursuit" not in stopped
    monkeypatch.setitem(controllers.CONTROLLER_FACTORIES, "route-pursuit", real)
    assert _run(out, "--controllers", "pac,route-pursuit", "--resume") == 0
    res = _results(out)
    assert res["pac"] == stopped["pac"] and res["route-pursuit"]["n_episodes"] == 1
    assert not res["meta"]["incomplete"] and res["meta"]["error"] is None


def test_resume_in_a_new_folder_runs_everything(tmp_path, capsys):
    assert _run(tmp_path / "new", "--controllers", "pac", "--resume") == 0
    assert "resume: no finished controller" in capsys.readouterr().out
    assert _results(tmp_path / "new")["meta"]["resumed"] == {}


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--seed", "7"], "has seed = 1000000, this command 7"),
        (["--env.action_delay", "1"], "has conditions = {}, this command {'action_delay': 1}"),
        (["--candidates", "4"], "has candidates = 10, this command 4"),
    ],
)
def test_resume_with_other_settings_is_one_error_naming_the_value(tmp_path, capsys, extra, message):
    out = tmp_path / "run"
    assert _run(out, "--controllers", "pac") == 0
    with pytest.raises(SystemExit) as e:
        _run(out, "--controllers", "pac,route-pursuit", "--resume", *extra)
    assert e.value.code == 2
    line = last_error_line(capsys.readouterr().err)
    assert line.startswith(f"error: --resume: the run in {out} ") and message in line, line
    assert "route-pursuit" not in _results(out)


@pytest.mark.parametrize(
    ("setup", "extra", "message"),
    [
        (None, ["--resume", "--overwrite"], "--resume keeps the finished controllers"),
        ("file", [], "is a file, not a folder"),
        ("broken", ["--resume"], "cannot be read as JSON"),
    ],
)
def test_bad_out_arguments(tmp_path, capsys, setup, extra, message):
    out = tmp_path / "run"
    if setup == "file":
        out.write_text("x")
    elif setup == "broken":
        out.mkdir()
        (out / "results.json").write_text("{not json")
    with pytest.raises(SystemExit) as e:
        _run(out, "--controllers", "pac", *extra)
    assert e.value.code == 2
    line = last_error_line(capsys.readouterr().err)
    assert line.startswith("error: ") and message in line and "\n" not in line


def _help(capsys) -> str:
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    return capsys.readouterr().out


def test_help_is_grouped_with_examples_and_a_line_per_controller(capsys, monkeypatch):
    monkeypatch.setitem(controllers.CONTROLLER_FACTORIES, "straight-line", "somewhere:make")
    monkeypatch.setitem(controllers.CONTROLLER_SUMMARIES, "straight-line", "drives straight to the goal")
    text = _help(capsys)
    for group in ("scenes:", "controllers:", "policy (", "conditions (", "output:", "speed:", "examples:"):
        assert f"\n{group}" in text, group
    assert text.count("\n  lerobot-formation-bench ") >= 3  # the examples
    for name in controllers.CONTROLLER_FACTORIES:  # derived from the registry, the new one included
        (line,) = [x for x in text.splitlines() if x.split()[:1] == [name]]
        assert line.split(None, 1)[1] == controllers.controller_summary(name)
    assert "drives straight to the goal" in text
    assert "``" not in text and "::" not in text  # no raw RST
    assert "adaptive" not in text.lower()  # a retired word
    # no default said twice: at most one "(default" in each option's help
    options = text.split("\noptions:")[1].split("\nexamples:")[0]
    for block in options.split("\n  --")[1:]:
        own = block.split("\n\n")[0]  # up to the next group's title
        assert own.count("(default") <= 1, own


def test_every_shipped_controller_has_a_summary():
    assert set(controllers.CONTROLLER_SUMMARIES) >= set(controllers.CONTROLLER_FACTORIES)
    assert results.RUN_FILES == ("results.json", "tables.md")


def test_merge_out_holding_a_run_is_refused_unless_overwrite(tmp_path, capsys):
    shards = [tmp_path / f"s{i}" for i in range(2)]
    for i, shard in enumerate(shards):
        assert _run(shard, "--controllers", "pac", "--scenes", "random:2", "--shard", f"{i}/2") == 0
    out = tmp_path / "merged"
    assert merge_main([*map(str, shards), "--out", str(out)]) == 0
    before = (out / "results.json").read_bytes()
    capsys.readouterr()
    assert merge_main([*map(str, shards), "--out", str(out)]) == 2
    assert last_error_line(capsys.readouterr().err) == (
        f"error: --out {out} already holds a run (results.json); add --overwrite to replace it, or choose "
        "another folder"
    )
    assert (out / "results.json").read_bytes() == before
    assert merge_main([*map(str, shards), "--out", str(out), "--overwrite"]) == 0
