"""Quiet, documented CLIs: summaries with and without --no-progress, no progress bars off a terminal,
help text on every option, and LeRobot's torchcodec/FFmpeg traceback cut to one line."""

import argparse
import dataclasses
import logging

import pytest
from draccus.wrappers.docstring import get_attribute_docstring, get_preferred_help_text

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
    assert "[random] pac: success" in out and "wrote" in out
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
    """draccus (lerobot-eval --help) shows a field's comment line above it."""
    for f in dataclasses.fields(FormationEnvConfig):
        text = get_preferred_help_text(get_attribute_docstring(FormationEnvConfig, f.name))
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
