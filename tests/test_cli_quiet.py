"""Quiet, documented CLIs: summaries with and without --no-progress, no progress bars off a terminal,
help text on every option, and LeRobot's torchcodec/FFmpeg traceback cut to one line."""

import argparse
import dataclasses
import logging
import os
import subprocess
import sys
from pathlib import Path

import draccus.argparsing
import pytest

import datasets_scripts.generate_pac_dataset as gen
from lerobot_formation.bench import cli as bench
from lerobot_formation.envs.env_config import FormationEnvConfig
from lerobot_formation.plugin import TORCHCODEC_NOTE, _TorchcodecLoadWarning, quiet_torchcodec_warning

BAR = ("ep/s", "s/ep", "it/s", "%|")  # pieces of a tqdm line


@pytest.mark.parametrize("no_progress", [True, False])
def test_bench_prints_its_summary_and_no_bar_off_a_terminal(no_progress, tmp_path, capsys):
    argv = ["--controllers", "pac", "--scenes", "random:2", "--out", str(tmp_path), "--no-figures"]
    assert bench.main(argv + ["--no-progress"] * no_progress) == 0
    out, err = capsys.readouterr()
    assert "[random:2] pac: success" in out and "wrote" in out
    assert not any(piece in err for piece in BAR), err  # captured stderr is not a terminal


@pytest.mark.parametrize("no_progress", [True, False])
def test_generator_prints_its_summary_and_no_bar_off_a_terminal(no_progress, tmp_path, capsys):
    argv = ["--episodes", "2", "--root", str(tmp_path / "ds")]
    assert gen.main(argv + ["--no-progress"] * no_progress) == 0
    out, err = capsys.readouterr()
    assert out.startswith("episodes 2, frames ") and str(tmp_path / "ds") in out
    assert not any(piece in err for piece in BAR), err


def _parser_of(main, argv, monkeypatch) -> argparse.ArgumentParser:
    """The argparse parser a CLI builds (caught at parse_args)."""
    seen = []
    real = argparse.ArgumentParser.parse_args

    def spy(self, *args, **kwargs):
        seen.append(self)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", spy)
    main(argv)
    return seen[0]


def test_every_generator_and_bench_option_has_help(monkeypatch):
    parsers = [_parser_of(gen.parse_args, ["--episodes", "1"], monkeypatch), bench.build_parser()]
    for ap in parsers:
        missing = [a.option_strings for a in ap._actions if a.option_strings and not a.help]
        assert not missing, f"{ap.prog}: options without help {missing}"


def test_every_env_config_field_has_draccus_help():
    """draccus (lerobot-eval --help) shows a help for every field: its comment line above it, or for a
    condition field the help declared with it in ``core.perception.conditions.Conditions``."""
    helps = {a.dest: a.help for a in draccus.argparsing.ArgumentParser(FormationEnvConfig).parser._actions}
    for f in dataclasses.fields(FormationEnvConfig):
        text = helps.get(f.name)
        assert text and text.strip(), f"--env.{f.name} has no help text"


def test_lerobot_eval_help_shows_the_env_options(run_cli, tmp_path):
    proc = run_cli("lerobot-eval", "--env.type=formation", "--help", cwd=tmp_path)
    lines = proc.stdout.splitlines()
    i = next(k for k, line in enumerate(lines) if line.strip().startswith("--env.obstacle_encoding"))
    assert "grid+list" in " ".join(lines[i : i + 4])
    assert "Traceback" not in proc.stderr


def test_torchcodec_warning_becomes_one_note(caplog):
    quiet_torchcodec_warning()  # idempotent: importing the plugin already installed it
    lerobot_logger = logging.getLogger("lerobot.utils.import_utils")
    assert sum(isinstance(f, _TorchcodecLoadWarning) for f in lerobot_logger.filters) == 1

    logger = logging.getLogger("test_cli_quiet.torchcodec")  # a fresh filter, not yet shown
    logger.addFilter(_TorchcodecLoadWarning())
    traceback = "Could not load libtorchcodec.\n[start of libtorchcodec loading traceback]\n" + "x\n" * 30
    with caplog.at_level(logging.WARNING, logger=logger.name):
        for _ in range(2):  # LeRobot logs it for every DatasetConfig / LeRobotDataset
            logger.warning(
                f"{traceback}\n'torchcodec' is installed but cannot be loaded (see the error above). "
                "Falling back to 'pyav' as a default decoder."
            )
        logger.warning("another warning")
    assert [r.getMessage() for r in caplog.records] == [TORCHCODEC_NOTE, "another warning"]
    assert "\n" not in TORCHCODEC_NOTE


@pytest.mark.slow  # ~25 s quiet, ~55 s on the shared 2-core machine
def test_lerobot_edit_dataset_merge_with_the_plugin_prints_no_traceback(tmp_path):
    """LeRobot's merge loads no plugin: through ``lerobot_formation.with_plugin`` it prints at most the
    one-line note (none where FFmpeg is installed), where it alone prints a traceback per dataset."""
    for i in range(2):
        argv = ["--episodes", "1", "--root", str(tmp_path / f"s{i}"), "--repo-id", f"local/s{i}"]
        assert gen.main(argv + ["--seed", str(i), "--no-progress"]) == 0
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent), "OMP_NUM_THREADS": "1"}
    args = [
        "lerobot-edit-dataset", "--new_repo_id", "local/merged", "--new_root", str(tmp_path / "merged"),
        "--operation.type", "merge", "--operation.repo_ids", "['local/s0','local/s1']",
        "--operation.roots", f"['{tmp_path / 's0'}','{tmp_path / 's1'}']",
    ]  # fmt: skip
    proc = subprocess.run(
        [sys.executable, "-m", "lerobot_formation.with_plugin", *args],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and "libtorchcodec" not in proc.stderr, proc.stderr[-3000:]
    assert proc.stderr.count("torchcodec cannot be loaded") <= 1
    assert (tmp_path / "merged" / "meta" / "info.json").is_file()


def test_with_plugin_names_the_lerobot_scripts_it_takes(capsys):
    from lerobot_formation.with_plugin import main

    assert main(["lerobot-nope"]) == 2
    err = capsys.readouterr().err
    assert "got 'lerobot-nope'" in err and "lerobot-edit-dataset" in err and "\n" == err[-1]


def test_the_demo_runs_the_shipped_default_against_the_baselines():
    """The README's main job finds the repository's pretrained default (it once looked one folder too
    high after a move and silently ran PAC and MPPI only)."""
    from lerobot_formation.bench import demo

    defaults = demo.default_arguments()
    assert defaults[defaults.index("--controllers") + 1] == "pac,mppi,diffusion,diffusion-safe"
    assert defaults[defaults.index("--scenes") + 1] == "level5:6"  # the hardest level's first unseen scenes
    assert "--unseen" not in defaults
    path = Path(defaults[defaults.index("--policy.path") + 1])
    assert (path / "config.json").is_file() and (path / "model.safetensors").is_file()
    # the demo before the 30-second one, as benchmarks/bench_demo_time.py reruns it
    previous = demo.PREVIOUS_ARGUMENTS
    assert previous[previous.index("--controllers") + 1] == "pac,mppi,diffusion,diffusion-bestof"
    assert previous[previous.index("--scenes") + 1] == "random:50" and "--all-figures" in previous


def test_the_demo_draws_the_focus_figures_and_states_its_numbers(tmp_path, capsys, monkeypatch):
    """Without --all-figures the demo draws three figures: the trajectories of one controller (the
    default with its layer; here PAC stands in, so no checkpoint is loaded), the controllers side by
    side and the success chart; then it prints each controller's successes of n with its Wilson interval."""
    from lerobot_formation.bench import cli as bench_cli
    from lerobot_formation.bench import demo

    monkeypatch.setattr(demo, "FOCUS", "pac")
    out = tmp_path / "demo"
    argv = ["--controllers", "pac,route-pursuit", "--scenes", "random:2", "--out", str(out), "--no-progress"]
    assert demo.main(argv) == 0
    assert bench_cli.draw_bench_figures is not demo.draw_demo_figures  # put back after the run
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("demo: pac,route-pursuit on random:2;") and "(unseen scenes)" in lines[0]
    drawn = {p.name for p in out.glob("*.png")}
    assert drawn == {"pac_random_trajectories.png", "controllers_random.png", "success_rates.png"}
    summary = [line for line in lines if line.startswith("demo:   ")]
    assert len(summary) == 2 and all(" of 2 " in line and "%]" in line for line in summary)
    assert "PAC (the paper's potential field)" in summary[0] and "(route-pursuit)" in summary[1]
    assert any(line.startswith("demo: 2 scenes are a first look") for line in lines)


def test_the_demo_lists_its_figures_once_and_names_its_sets(tmp_path, capsys):
    from lerobot_formation.bench.demo import main as demo_main

    out = tmp_path / "demo"
    argv = ["--controllers", "pac", "--scenes", "random:2", "--unseen", "hard:4", "--out", str(out)]
    assert demo_main(argv + ["--no-progress"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "both sets are unseen" in lines[0] and "random:2" in lines[0] and "hard:4" in lines[0]
    assert "scene seeds from 1000000 on" in lines[0]
    assert any(line.startswith("[random:2] pac: success") for line in lines)
    figure_lines = [line for line in lines if "pac_random_trajectories.png" in line]
    assert len(figure_lines) == 1, lines
    assert lines[-1].startswith("demo: done in ") and str(out / "tables.md") in lines[-1]
    assert "figures listed above" in lines[-1]


def test_generator_summary_counts_what_it_ran_and_names_the_hub_folder():
    summary = {"episodes": 20, "frames": 100, "mb": 0.1, "seconds": 1.0}
    summary.update(pac_attempted=23, pac_succeeded=23, pac_success_rate=1.0, pushed_to="hub/local/x")
    line = gen.summary_line(summary, "data/x")
    assert "episodes 20," in line and "PAC succeeded on 23 of 23 scenes (100.0%)" in line
    assert "the first 20 successes kept" in line and line.endswith("-> data/x; hub folder -> hub/local/x")
    summary.update(pac_attempted=25, pac_succeeded=20, pac_success_rate=0.8, pushed_to=None)
    line = gen.summary_line(summary, "data/x")
    assert "PAC succeeded on 20 of 25 scenes (80.0%)," in line and "kept" not in line and "hub" not in line


@pytest.mark.parametrize("build", ["bench", "generator"])
def test_help_shows_the_defaults(build, monkeypatch, capsys):
    ap = (
        bench.build_parser()
        if build == "bench"
        else _parser_of(gen.parse_args, ["--episodes", "1"], monkeypatch)
    )
    text = " ".join(ap.format_help().split())
    assert "(default: 1000000" in text if build == "bench" else "(default: 1878)" in text


@pytest.mark.slow  # a fresh interpreter importing LeRobot: ~15 s quiet, ~45 s on the shared machine
def test_loading_a_dataset_after_the_plugin_prints_at_most_one_note(tmp_path):
    """The docs' LeRobotDataset load (``import lerobot_formation.plugin`` first): no FFmpeg traceback."""
    assert gen.main(["--episodes", "1", "--root", str(tmp_path / "ds"), "--no-progress"]) == 0
    code = (
        "import lerobot_formation.plugin; from lerobot.datasets.lerobot_dataset import LeRobotDataset as D; "
        f"print(D('local/formation_pac', root={str(tmp_path / 'ds')!r}).num_episodes)"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and proc.stdout.strip() == "1", proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and "libtorchcodec" not in proc.stderr, proc.stderr[-3000:]
    assert len(proc.stderr.strip().splitlines()) <= 1, proc.stderr
