"""``--threads N`` (lerobot_formation/threads.py): the default rule, the flag, what it sets, and that
the console scripts list it."""

import argparse
import os
import sys

import pytest

from lerobot_formation.threads import (
    ENV_VAR,
    THREAD_ENV_VARS,
    add_threads_argument,
    apply_threads,
    default_threads,
)


@pytest.mark.parametrize(
    ("env", "expected"),
    [
        ({}, 1),
        ({"OMP_NUM_THREADS": "3"}, 3),
        ({ENV_VAR: "2", "OMP_NUM_THREADS": "3"}, 2),  # the project's variable wins
        ({ENV_VAR: "", "OMP_NUM_THREADS": "4"}, 4),  # empty falls through
        ({ENV_VAR: "zero", "OMP_NUM_THREADS": "0"}, 1),  # not a whole number >= 1 falls through
        ({ENV_VAR: " 5 "}, 5),
    ],
)
def test_default_rule(env, expected):
    assert default_threads(env) == expected


def test_flag_parses_and_defaults_from_the_environment(monkeypatch):
    monkeypatch.delenv(ENV_VAR, raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    ap = argparse.ArgumentParser()
    add_threads_argument(ap)
    assert ap.parse_args([]).threads == 1
    assert ap.parse_args(["--threads", "2"]).threads == 2
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    ap = argparse.ArgumentParser()
    add_threads_argument(ap)
    assert ap.parse_args([]).threads == 3
    for bad in ("0", "-1", "two"):
        with pytest.raises(SystemExit):
            ap.parse_args(["--threads", bad])


def test_apply_sets_torch_and_the_variables_for_children(monkeypatch):
    for name in THREAD_ENV_VARS:
        monkeypatch.setenv(name, "7")  # restored by monkeypatch after the test
    import torch  # the conftest fixture restores torch's thread count

    assert "torch" in sys.modules
    assert apply_threads(2) == 2
    assert torch.get_num_threads() == 2
    assert all(os.environ[name] == "2" for name in THREAD_ENV_VARS)
    with pytest.raises(ValueError):
        apply_threads(0)


@pytest.mark.parametrize("script", ["lerobot-formation-bench", "lerobot-formation-generate"])
def test_console_scripts_list_threads(script, run_cli, tmp_path):
    proc = run_cli(script, "--help", cwd=tmp_path)
    assert "--threads N" in proc.stdout and ENV_VAR in proc.stdout


def _main_of(relpath: str):
    """``main`` of a repository script that is not an installed module (scripts/, benchmarks/)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / relpath
    spec = importlib.util.spec_from_file_location(f"_threads_test_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main


@pytest.mark.parametrize(
    "cli",
    [
        "lerobot_formation.bench.demo",
        "datasets_scripts.dagger_scenes",
        "scripts/checkpoint_curve.py",
        "benchmarks/bench_eval_speed.py",
        "benchmarks/bench_replan_latency.py",
    ],
)
def test_every_other_cli_takes_threads(cli, capsys):
    if cli.endswith(".py"):
        main = _main_of(cli)
    else:
        import importlib

        main = importlib.import_module(cli).main
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    assert "--threads N" in capsys.readouterr().out
