"""scripts/make_gif.py: the README's animation of an episode (a valid GIF of several frames, written
atomically, an existing file refused without --overwrite) and its frame choice."""

import importlib.util
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _script():
    path = REPO / "scripts" / "make_gif.py"
    spec = importlib.util.spec_from_file_location("_make_gif_test", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_frame_steps_keep_the_last_step_and_fit_the_frame_limit():
    m = _script()
    assert m.frame_steps(10, 3, 150) == [0, 3, 6, 9, 10]
    assert m.frame_steps(9, 3, 150) == [0, 3, 6, 9]
    steps = m.frame_steps(600, 3, 150)
    assert len(steps) <= 150 and steps[0] == 0 and steps[-1] == 600


def test_an_existing_gif_is_refused_before_anything_runs(tmp_path, capsys):
    out = tmp_path / "episode.gif"
    out.write_bytes(b"kept")
    with pytest.raises(SystemExit) as exit_info:
        _script().main(["--out", str(out)])
    assert exit_info.value.code == 2
    assert "exists; add --overwrite" in capsys.readouterr().err
    assert out.read_bytes() == b"kept"


@pytest.mark.slow
def test_the_default_s_episode_becomes_an_animated_gif(tmp_path, capsys):
    """A tiny episode (12 control steps of the shipped default with its safety layer on the script's
    level5 scene) gives a GIF of several frames; a second run needs --overwrite and leaves no temporary file."""
    from PIL import Image

    m = _script()
    out = tmp_path / "gifs" / "episode.gif"
    argv = ["--out", str(out), *"--max-steps 12 --every 3 --fps 10 --dpi 40 --threads 1".split()]
    assert m.main(argv) == 0
    with Image.open(out) as gif:
        assert gif.format == "GIF" and gif.is_animated
        frames = gif.n_frames
    hold = round(m.HOLD_S * 10)
    assert frames >= 5 and frames <= 5 + hold  # steps 0, 3, 6, 9, 12 (identical held frames may merge)
    printed = capsys.readouterr().out
    assert (
        "(diffusion-safe), level5 scene 2 (seed 1000002): timeout after 1.2 s" in printed
        and f"wrote {out}" in printed
    )
    with pytest.raises(SystemExit):
        m.main(argv)
    assert m.main(argv + ["--overwrite"]) == 0
    assert [p.name for p in out.parent.iterdir()] == ["episode.gif"]
