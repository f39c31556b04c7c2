"""Every script in scripts/ and benchmarks/ runs (issue 61, item 5: scripts run or go).

The scripts are found by globbing the two folders, so a new one is tested without being listed here:

- fast: each runs with ``--help`` in a subprocess, as a user starts it (``python X.py --help``, a shell
  script by its own path), exits 0 and prints a usage line and a description;
- fast: ``SMOKES`` has an entry for every script (and for no script that is gone);
- slow: each script's smoke run at tiny sizes (a scene or two, tiny models or the shipped small one,
  a step or two), into ``tmp_path``, checked by a line of its output and the files it writes.

A Python script's smoke calls its ``main(argv)`` in this process (torch and LeRobot are imported once
for all of them; the subprocess ``--help`` run covers the ``__main__`` guard), with the environment
restored after; ``Smoke.subprocess`` runs it as a program instead where it changes this process for
good (``bench_train_throughput.py`` installs a reader patch into LeRobot). Shell scripts always run as
programs. An entry may be a string instead: why that script has no smoke run (it still has ``--help``).
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
FOLDERS = ("scripts", "benchmarks")
SUFFIXES = (".py", ".sh")
ROUTE = str(REPO / "pretrained" / "formation_diffusion_route_v1")
TINY_CONFIG = str(REPO / "configs" / "formation_diffusion_tiny.json")
ENV = {"HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
THREADS = ["--threads", "1"]


def discovered() -> list[str]:
    """Every script of scripts/ and benchmarks/ (repository-relative paths)."""
    return sorted(
        p.relative_to(REPO).as_posix()
        for folder in FOLDERS
        for p in (REPO / folder).iterdir()
        if p.is_file() and p.suffix in SUFFIXES
    )


class Ctx:
    """What a smoke's arguments are built from: its own folder and the shared tiny inputs (built on
    first use, once per module)."""

    def __init__(self, request, tmp: Path):
        self.request, self.tmp = request, tmp

    @property
    def dataset(self) -> Path:
        """A 2-episode PAC dataset, "grid" encoding (configs/formation_diffusion_tiny.json's)."""
        return self.request.getfixturevalue("tiny_dataset")

    @property
    def bench_run(self) -> Path:
        """A bench output folder: PAC on level0's first scene."""
        return self.request.getfixturevalue("pac_level0_run")

    def p(self, name: str) -> str:
        return str(self.tmp / name)


@dataclass(frozen=True)
class Smoke:
    """``calls``: the argument lists of the script's runs, in order; ``expect``: a text the output
    holds; ``files``: paths under the smoke's folder that must exist after; ``check``: more checks on
    that folder; ``subprocess``: run as a program (always for shell scripts)."""

    calls: Callable[[Ctx], list[list[str]]]
    expect: str
    files: tuple[str, ...] = ()
    check: Callable[[Path], None] | None = None
    subprocess: bool = False


def _derived_margin(tmp: Path) -> None:
    assert json.loads((tmp / "derived" / "config.json").read_text())["safety_margin"] == 0.07


def _exported(tmp: Path) -> None:
    cfg = json.loads((tmp / "exported" / "config.json").read_text())
    assert cfg["use_ema"] is False
    assert len(json.loads((tmp / "exported" / "dataset_scenes.json").read_text())["scenes"]) == 2


def _training_checkpoint(ctx: Ctx) -> str:
    """A lerobot-train checkpoint folder as export_pretrained.py reads it: the shipped weights stored
    twice, as the model's and as its EMA copy (``ema_diffusion.*``), and the checkpoint's other files."""
    import shutil

    from safetensors.torch import load_file, save_file

    ckpt = ctx.tmp / "train" / "checkpoints" / "000004" / "pretrained_model"
    ckpt.mkdir(parents=True)
    state = load_file(Path(ROUTE) / "model.safetensors")
    save_file({**state, **{f"ema_{k}": v.clone() for k, v in state.items()}}, ckpt / "model.safetensors")
    for f in Path(ROUTE).iterdir():
        if f.name == "config.json" or f.name.startswith("policy_") or f.name == "train_config.json":
            shutil.copy(f, ckpt / f.name)
    return str(ckpt)


def _curve_run(ctx: Ctx) -> str:
    """A lerobot-train output folder with one numbered checkpoint (a link to the shipped model)."""
    step = ctx.tmp / "run" / "checkpoints" / "000100"
    step.mkdir(parents=True)
    (step / "pretrained_model").symlink_to(ROUTE, target_is_directory=True)
    return str(ctx.tmp / "run")


# the bench run that level_table.py and publish_tables.py read (the ``pac_level0_run`` fixture)
BENCH_COMMAND = (
    "lerobot-formation-bench --controllers pac --scenes level0:1 --no-figures --no-progress --threads 1"
)
PUBLISH_SPEC = """
[tables.tiny]
label = "controller"
rows = [{ controller = "pac", label = "PAC" }]
columns = [
    { header = "level0:1", artifact = "tiny", value = "success" },
    { header = "episodes", artifact = "tiny", value = "n" },
]
"""


def _publish_root(ctx: Ctx) -> str:
    root = ctx.tmp / "root"
    (root / "results").mkdir(parents=True)
    (root / "results" / "tables.toml").write_text(PUBLISH_SPEC)
    (root / "README.md").write_text("# tiny\n\n<!-- table:tiny -->\n<!-- /table:tiny -->\n")
    return str(root)


def _published(tmp: Path) -> None:
    readme = (tmp / "root" / "README.md").read_text()
    assert "| PAC |" in readme, readme


def _run_sh_current() -> str | None:
    """Why scripts/run.sh cannot run here without installing anything (None: it can)."""
    import hashlib

    venv = REPO / ".venv"
    if Path(sys.executable).parent != venv / "bin":
        return f"scripts/run.sh runs .venv/bin/python, these tests run {sys.executable}"
    stamp = venv / ".installed"
    want = hashlib.sha256((REPO / "pyproject.toml").read_bytes()).hexdigest()[:16]
    if not stamp.is_file() or stamp.read_text().strip() != want:
        return ".venv/.installed does not match pyproject.toml: scripts/run.sh would reinstall the project"
    return None


# script -> its smoke run, or why it has none
SMOKES: dict[str, Smoke | str] = {
    "scripts/ablation.py": Smoke(
        lambda c: [
            ["--new", ROUTE, "--sets", "random:1", "--candidates", "2", "--out", c.p("ablation")]
            + ["--rows", "PAC;new, best-of-2 + CBF + escapes"]
        ],
        expect="| new, best-of-2 + CBF + escapes | ",
        files=("ablation/ablation.md", "ablation/ablation.json"),
    ),
    "scripts/checkpoint_curve.py": Smoke(
        lambda c: [
            [_curve_run(c), "--scenes", "random:1", "--target", "0", "--out", c.p("curve.json"), *THREADS]
        ],
        expect="first checkpoint at >= 0 %: step 100",
        files=("curve.json",),
    ),
    "scripts/collision_report.py": Smoke(
        lambda c: [["--controller", "pac-privileged", "--level", "level5", "--scenes", "1", *THREADS]],
        expect="pac-privileged on level5 (1 scenes from seed",
    ),
    "scripts/derive_checkpoint.py": Smoke(
        lambda c: [[ROUTE, c.p("derived"), "--set", "safety_margin=0.07"]],
        expect="(safety_margin=0.07;",
        files=("derived/model.safetensors", "derived/policy_preprocessor.json"),
        check=_derived_margin,
    ),
    "scripts/export_pretrained.py": Smoke(
        lambda c: [
            [_training_checkpoint(c), c.p("exported"), "--dataset.root", str(c.dataset), "--scenes", "2"]
        ],
        expect="wrote ",
        files=("exported/model.safetensors", "exported/README.md"),
        check=_exported,
    ),
    "scripts/gpu_hintfree_paper.sh": (
        "a CUDA run of minutes (1,200 episodes, lerobot-train, six levels; docs/log.md), written to fixed "
        "folders under data/ and outputs/: nothing of it is tiny"
    ),
    "scripts/jerk_sources.py": Smoke(
        lambda c: [["--policy.path", ROUTE, "--level", "level0", "--scenes", "1", *THREADS]],
        expect="diffusion-safe on level0 (1 scenes from seed",
    ),
    "scripts/level_table.py": Smoke(
        lambda c: [[str(c.bench_run)], ["--compact", str(c.bench_run)]],
        expect="| PAC",
    ),
    "scripts/make_gif.py": Smoke(
        lambda c: [
            ["--controller", "pac", "--scenes", "level0:1", "--scene", "0", "--max-steps", "12"]
            + ["--dpi", "30", "--size", "2", "--out", c.p("episode.gif")]
        ],
        expect="wrote ",
        files=("episode.gif",),
    ),
    "scripts/publish_tables.py": Smoke(
        lambda c: [
            ["--add", "tiny", str(c.bench_run), "--root", _publish_root(c), "--command", BENCH_COMMAND],
            ["--check", "--root", c.p("root")],
        ],
        expect="tables written from results/",
        files=("root/results/tiny.json",),
        check=_published,
    ),
    "scripts/run.sh": Smoke(
        lambda c: [
            ["demo", "--controllers", "pac", "--scenes", "level0:1", "--no-figures", "--no-progress"]
            + ["--out", c.p("demo")]
        ],
        expect="demo: done in",
        files=("demo/results.json",),
        subprocess=True,
    ),
    "benchmarks/bench_dataset.py": Smoke(
        lambda c: [["--episodes", "2", "--write-episodes", "2"]],
        expect="writer speed-up vs add_frame:",
    ),
    "benchmarks/bench_demo_time.py": Smoke(
        lambda c: [["--quick", *THREADS, "--work-dir", c.p("work"), "--", "--controllers", "pac"]],
        expect="demo wall time: new",
        files=("work/new_0.log", "work/previous_0.log"),
    ),
    "benchmarks/bench_env_step.py": Smoke(
        lambda c: [["--batch", "4", "--steps", "2", "--repeats", "1"]],
        expect="conditions on / off step cost:",
    ),
    "benchmarks/bench_eval_speed.py": Smoke(
        lambda c: [
            ["--policy.path", ROUTE, "--episodes", "1", "--episode-length", "20", "--stock", "1:sync"]
            + [*THREADS, "--out", c.p("eval")]
        ],
        expect="ratio lerobot-eval best / engine (evaluation time):",
        files=("eval/scenes.json",),
    ),
    "benchmarks/bench_follower_floor.py": Smoke(
        lambda c: [["--steps", "21", "--batch", "2", "--repeats", "1"]],
        expect="floor ratio sign() / boundary layer at 1 ms:",
    ),
    "benchmarks/bench_refusals.py": Smoke(
        lambda c: [["--scenes", "10", "--repeats", "1"]],
        expect="refusal / the work it spares: far goal",
    ),
    "benchmarks/bench_replan_latency.py": Smoke(
        lambda c: [
            ["--quick", "--parts", "abc", "--policy.path", ROUTE, "--paper-config", TINY_CONFIG]
            + ["--ddim-steps", "2", "--batch", "2", "--lean-candidates", "1", "2", "--lean-steps", "2"]
            + ["--lean-repeats", "1", *THREADS]
        ],
        expect="replan latency B=1 K=1:",
    ),
    "benchmarks/bench_route_encoding.py": Smoke(
        lambda c: [["--scenes", "1", "--steps", "2"]],
        expect="step with the route hint:",
    ),
    "benchmarks/bench_sampling_steps.py": Smoke(
        lambda c: [
            ["--policy.path", ROUTE, "--scenes", "random:1", "--steps", "1", "--reference", "2"]
            + [*THREADS, "--out", c.p("steps.json")]
        ],
        expect="fastest sampler within noise of DDIM 2",
        files=("steps.json",),
    ),
    "benchmarks/bench_setup_probe.py": Smoke(
        lambda c: [["--repeats", "1"]],
        expect="unreachable index / no probe:",
    ),
    "benchmarks/bench_train_throughput.py": Smoke(
        lambda c: [
            ["--dataset.root", str(c.dataset), "--dataset.repo_id", "local/smoke", "--config", TINY_CONFIG]
            + ["--batch-size", "4", "--steps", "2", "--warmup", "1", "--num-workers", "0", "--fast-reads"]
        ],
        expect="ratio pure compute / with loader:",
        subprocess=True,  # --fast-reads installs a reader patch into LeRobot for good
    ),
    "benchmarks/bench_unet_backends.py": Smoke(
        lambda c: [["--batch", "1", "--repeats", "1", *THREADS]],
        expect="policy trace vs plain trace:",
    ),
    "benchmarks/mppi_sweep.py": Smoke(
        lambda c: [
            ["--scenes", "1", "--confirm", "1", "--settings", "K=64", "--out", c.p("mppi.json")],
        ],
        expect="## Confirmation of `K=64`",
        files=("mppi.json",),
    ),
}

SCRIPTS = discovered()

# flags a script's --help must list (beyond a usage line and a description)
HELP_FLAGS: dict[str, list[str]] = {
    "benchmarks/bench_demo_time.py": ["--quick", "--threads N", "--load", "--via-run-sh", "-- DEMO ARGS"],
    "benchmarks/bench_unet_backends.py": ["--batch", "--repeats", "--threads N", "--policy.path"],
    "benchmarks/bench_sampling_steps.py": ["--quick", "--threads N", "--steps", "--scenes", "--controller"]
    + ["--inference-backend", "--out", "--spacings"],
}


def _program(script: str) -> list[str]:
    """The command line that starts ``script``: a shell script by its path (it must be executable)."""
    path = REPO / script
    return [str(path)] if path.suffix == ".sh" else [sys.executable, str(path)]


def _run_program(script: str, args: list[str], cwd: Path, timeout: int) -> tuple[int, str]:
    proc = subprocess.run(
        [*_program(script), *args],
        cwd=cwd,
        env={**os.environ, **ENV},
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    return proc.returncode, proc.stdout + proc.stderr


def _load(script: str):
    path = REPO / script
    spec = importlib.util.spec_from_file_location(f"_smoke_{path.parent.name}_{path.stem}", path)
    module = sys.modules[spec.name] = importlib.util.module_from_spec(spec)  # dataclasses look it up
    spec.loader.exec_module(module)
    return module


@contextlib.contextmanager
def _environment_kept():
    """os.environ as it was after the block (scripts set their thread variables)."""
    saved = dict(os.environ)
    try:
        os.environ.update(ENV)
        yield
    finally:
        os.environ.clear()
        os.environ.update(saved)


# --- fast ----------------------------------------------------------------------------------------


def test_the_scripts_are_found():
    assert {"scripts/run.sh", "scripts/ablation.py", "benchmarks/bench_replan_latency.py"} <= set(SCRIPTS)


def test_every_script_has_a_smoke_entry():
    """A new script needs an entry in SMOKES (its smoke run, or why it has none); a removed one's goes."""
    missing = sorted(set(SCRIPTS) - set(SMOKES))
    gone = sorted(set(SMOKES) - set(SCRIPTS))
    assert not missing, f"scripts without an entry in SMOKES (tests/scripts/test_scripts_smoke.py): {missing}"
    assert not gone, f"entries in SMOKES for scripts that are gone: {gone}"


@pytest.mark.parametrize("script", SCRIPTS)
def test_help(script):
    """``--help`` exits 0 and prints the usage and a description (a paragraph before the options)."""
    if script.endswith(".sh"):
        assert os.access(REPO / script, os.X_OK), f"{script} is not executable"
    code, out = _run_program(script, ["--help"], REPO, timeout=120)
    assert code == 0, f"{script} --help exited {code}:\n{out[-3000:]}"
    paragraphs = [p.strip() for p in out.strip().split("\n\n") if p.strip()]
    assert paragraphs and paragraphs[0].lower().startswith("usage:"), out
    assert len(paragraphs) > 1 and not paragraphs[1].startswith(("options:", "positional arguments:")), (
        f"{script} --help has no description:\n{out}"
    )
    for flag in HELP_FLAGS.get(script, []):
        assert flag in out, f"{script} --help lacks {flag!r}:\n{out}"


# --- slow ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory) -> Path:
    from datasets_scripts.generate_pac_dataset import main as generate

    root = tmp_path_factory.mktemp("dataset") / "formation_pac_smoke"
    with _environment_kept():
        argv = ["--episodes", "2", "--obstacle-encoding", "grid", "--root", str(root)]
        assert generate([*argv, "--repo-id", "local/smoke", "--no-progress", *THREADS]) == 0
    return root


@pytest.fixture(scope="module")
def pac_level0_run(tmp_path_factory) -> Path:
    from lerobot_formation.bench.cli import main as bench

    out = tmp_path_factory.mktemp("bench") / "level0"
    with _environment_kept():
        assert bench([*BENCH_COMMAND.split()[1:], "--out", str(out)]) == 0
    return out


@pytest.mark.slow
@pytest.mark.parametrize("script", SCRIPTS)
def test_smoke(script, request, tmp_path, capsys, monkeypatch):
    if script not in SMOKES:
        pytest.fail(f"{script} has no entry in SMOKES (tests/scripts/test_scripts_smoke.py)")
    smoke = SMOKES[script]
    if isinstance(smoke, str):
        pytest.skip(f"{script}: no smoke run: {smoke}")
    if script == "scripts/run.sh" and (why := _run_sh_current()):
        pytest.skip(why)
    ctx = Ctx(request, tmp_path)
    calls = smoke.calls(ctx)
    capsys.readouterr()  # the fixtures' output is not the script's
    outputs = []
    if smoke.subprocess or script.endswith(".sh"):
        for argv in calls:
            code, out = _run_program(script, argv, tmp_path, timeout=300)
            assert code == 0, f"{script} {' '.join(argv)} exited {code}:\n{out[-4000:]}"
            outputs.append(out)
    else:
        module = _load(script)
        monkeypatch.chdir(tmp_path)  # whatever a script writes by a relative path lands here
        for argv in calls:
            with _environment_kept():
                code = module.main(argv)
            captured = capsys.readouterr()
            out = captured.out + captured.err
            assert code in (0, None), f"{script} {' '.join(argv)} returned {code}:\n{out[-4000:]}"
            outputs.append(out)
    text = "\n".join(outputs)
    assert smoke.expect in text, f"{script}: {smoke.expect!r} not in its output:\n{text[-4000:]}"
    for name in smoke.files:
        assert (tmp_path / name).exists(), f"{script} did not write {name}"
    if smoke.check:
        smoke.check(tmp_path)
