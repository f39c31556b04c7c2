"""scripts/level_table.py: the level table from bench output folders."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _script():
    spec = importlib.util.spec_from_file_location("level_table", ROOT / "scripts" / "level_table.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _metrics(success: float, collisions: int, safety: dict | None = None) -> dict:
    m = {
        "n_episodes": 10,
        "success_rate": success,
        "success_ci95": [success - 0.1, min(success + 0.05, 1.0)],
        "collisions": collisions,
        "timeouts": 0,
        "control_smoothness": {"mean": 0.5},
        "jerk": {"mean": 0.25},
        "min_clearance": {"mean": 1.0},
    }
    if safety is not None:
        m["safety"] = safety
    return m


def _write(folder: Path, scenes: str, **controllers) -> Path:
    folder.mkdir()
    results = {k.replace("_", "-"): v for k, v in controllers.items()}
    results["meta"] = {"scenes": scenes}
    (folder / "results.json").write_text(json.dumps(results))
    return folder


def test_rows_per_level_in_controller_order_and_a_later_folder_wins(tmp_path, capsys):
    safety = {"steps": 1000, "filter_intervention_rate": 0.025, "replans_none_safe_rate": 0.1}
    a = _write(
        tmp_path / "a",
        "level5:10",
        diffusion_safe=_metrics(0.4, 6, safety),
        pac=_metrics(0.5, 5),
    )
    b = _write(tmp_path / "b", "level5:10", diffusion_safe=_metrics(0.6, 4, safety))
    c = _write(tmp_path / "c", "level0:10", diffusion=_metrics(1.0, 0, {"steps": 1000}))
    _script().main([str(a), str(b), str(c), "--name", "pac=the demonstrator"])
    rows = capsys.readouterr().out.splitlines()[2:]
    assert rows == [
        "| level0 (10) | default, standard | 100.0 [90, 100] | 0 / 0 | 0.500 | 0.250 | 1.000 | - |",
        "| level5 (10) | the demonstrator | 50.0 [40, 55] | 5 / 0 | 0.500 | 0.250 | 1.000 | - |",
        "| level5 (10) | default, best-of-10 + CBF | 60.0 [50, 65] | 4 / 0 | 0.500 | 0.250 | 1.000 "
        "| 2.50 / 10.0 |",
    ]


def test_a_folder_without_results_is_named(tmp_path, capsys):
    with pytest.raises(SystemExit):
        _script().main([str(tmp_path)])
    assert f"{tmp_path} holds no results.json" in capsys.readouterr().err


def test_a_tagged_folder_stands_beside_the_default_in_the_compact_table(tmp_path, capsys):
    a = _write(tmp_path / "a", "level3:10", pac=_metrics(0.5, 5), diffusion=_metrics(0.7, 3))
    b = _write(tmp_path / "b", "level3:10", diffusion=_metrics(0.2, 8))
    _script().main(["--compact", str(a), f"{b}@hf", "--name", "diffusion@hf=hint-free"])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "| level | PAC | default, standard | hint-free |"
    assert lines[2] == (
        "| level3 | 50.0 [40, 55], 5/0 (10) | 70.0 [60, 75], 3/0 (10) | 20.0 [10, 25], 8/0 (10) |"
    )


def test_collisions_show_how_many_a_mover_struck_where_counted(tmp_path, capsys):
    struck = dict(_metrics(0.5, 5), struck_by_mover=3)
    none_struck = dict(_metrics(0.9, 1), struck_by_mover=0)
    a = _write(tmp_path / "a", "level5:10", pac=struck, route_pursuit=none_struck)
    _script().main([str(a)])
    rows = capsys.readouterr().out.splitlines()[2:]
    assert rows[0].startswith("| level5 (10) | PAC | 50.0 [40, 55] | 5 (3 struck) / 0 |")
    assert rows[1].startswith("| level5 (10) | route pursuit | 90.0 [80, 95] | 1 / 0 |")
    _script().main([str(a), "--compact"])
    assert capsys.readouterr().out.splitlines()[2] == (
        "| level5 | 50.0 [40, 55], 5 (3 struck)/0 (10) | 90.0 [80, 95], 1/0 (10) |"
    )
