"""The README and docs/*.md stay current (issues 13 and 27).

Fast checks, running nothing but parsers:
- every ```bash block parses (``bash -n``);
- every command in those blocks runs a program that exists and takes the flags it is given: the
  project's argparse CLIs parse the whole command line with their own parser, LeRobot's draccus CLIs
  are checked against their own help text (scoped to the formation env and policy);
- every repository path the docs mention (in backticks, links or commands) exists. The check is
  generic: a path counts when its first component is a top-level entry of the repository (or a
  subpackage of ``lerobot_formation``, for short paths such as ``core/world/scenes.py``); a bare file name
  such as ``controllers.py`` must exist somewhere in the package. Moving a module only means fixing
  the docs' paths;
- every folder the docs' commands write at the repository root is git-ignored.

End to end: the README's dataset journey (generator, scaled to 2 episodes) in the fast tier, and the
README's four journeys (dataset, train, eval, bench) scaled down in the ``slow`` tier.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.metadata
import importlib.util
import inspect
import io
import os
import re
import runpy
import shlex
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
# docs/log.md records experiments: its commands ran with the flags and files of their date, so only
# its bash blocks are checked to parse; every other page's commands and paths must work as they are.
LOG = REPO / "docs" / "log.md"
CURRENT = [doc for doc in DOCS if doc != LOG]
BIN = Path(sys.executable).parent

# Console script -> the draccus-wrapped function of its module (None: an argparse program).
CONSOLE_SCRIPTS = {
    "lerobot-formation-generate": None,
    "lerobot-formation-bench": None,
    "lerobot-formation-bench-merge": None,
    "lerobot-train": "train",
    "lerobot-eval": "eval_main",
    "lerobot-edit-dataset": "edit_dataset",
}
DRACCUS_DEFAULT_TYPES = {"policy": "formation_diffusion", "env": "formation"}
RUN_SH = {"demo": "python -m lerobot_formation.bench.demo", "test": None, "setup": None}
WRAPPER = "python -m lerobot_formation.with_plugin"  # runs the LeRobot script named next
# docs/ files other helpers write in parallel (issue 27); the lead empties this at the merge.
WRITTEN_ELSEWHERE = {"docs/design.md", "docs/data-safety.md"}
WRITE_FLAGS = ("--root", "--out", "--output_dir", "--push-to", "--new_root")


@dataclass
class Command:
    line: str
    program: str
    args: list[str]
    env: dict[str, str] = field(default_factory=dict)

    def flags(self) -> list[str]:
        return [a.split("=", 1)[0] for a in self.args if a.startswith("--")]

    def value(self, flag: str) -> str | None:
        for i, a in enumerate(self.args):
            if a.startswith(flag + "="):
                return a.split("=", 1)[1]
            if a == flag and i + 1 < len(self.args):
                return self.args[i + 1]
        return None

    def __str__(self) -> str:
        return self.line if len(self.line) < 90 else self.line[:87] + "..."


# --- parsing the docs ----------------------------------------------------------------------------

FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```", re.S | re.M)


def bash_blocks(path: Path) -> list[str]:
    return [m.group(2) for m in FENCE.finditer(path.read_text()) if m.group(1) == "bash"]


def bash_lines(block: str) -> list[str]:
    """Logical lines (continuations joined, comments dropped)."""
    lines = re.sub(r"\s*\\\n\s*", " ", block).splitlines()
    return [line.strip() for line in lines if line.strip() and not line.lstrip().startswith("#")]


def _tokens(line: str) -> list[str]:
    line = re.sub(r"\$\(which ([\w.-]+)\)", r"\1", line)  # accelerate launch $(which lerobot-train)
    lexer = shlex.shlex(line, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    return list(lexer)


def _expand_loops(tokens: list[str]) -> list[str]:
    """``for V in a b; do BODY & done; wait`` -> BODY with $V=a ; BODY with $V=b ; wait."""
    if not tokens or tokens[0] != "for":
        return tokens
    if "do" not in tokens:
        return []
    var, i = tokens[1], tokens.index("do")
    head = tokens[3:i]
    values = head[: head.index(";")] if ";" in head else head
    if any("$" in v or "(" in v for v in values):  # a computed list ($(seq ...)): one stand-in value
        values = ["0"]
    # a loop over several lines: its body's commands are on lines of their own
    j = len(tokens) - 1 - tokens[::-1].index("done") if "done" in tokens else len(tokens)
    out = []
    for v in values:
        out += [t.replace(f"${var}", v) for t in tokens[i + 1 : j]] + [";"]
    return out + tokens[j + 1 :]


def parse_commands(line: str) -> list[Command]:
    commands, current = [], []
    redirect = False
    for tok in _expand_loops(_tokens(line)) + [";"]:
        if redirect:  # the target of a redirection (> FILE, 2>&1)
            redirect = False
            continue
        if tok in (">", ">>", "<", ">&", "&>"):
            if current and current[-1] in ("1", "2"):  # the 2 of 2>&1
                current.pop()
            redirect = True
            continue
        if tok in (";", "&", "&&", "||", "|"):
            if current:
                commands.append(_command(line, current))
            current = []
        else:
            current.append(tok)
    return [c for c in commands if c is not None]


def _command(line: str, tokens: list[str]) -> Command | None:
    env = {}
    while tokens and re.fullmatch(r"[A-Z_][A-Z0-9_]*=\S*", tokens[0]):
        key, value = tokens.pop(0).split("=", 1)
        env[key] = value
    if not tokens or tokens[0] in ("wait", "source", "time"):
        return None
    if tokens[0] == "accelerate":  # accelerate launch [its options] PROGRAM args
        tokens = tokens[next(i for i, t in enumerate(tokens) if t in CONSOLE_SCRIPTS) :]
    if " ".join(tokens[:3]) == WRAPPER:
        tokens = tokens[3:]
    if tokens[0] == "python" and len(tokens) > 2 and tokens[1] == "-m":
        return Command(line, f"python -m {tokens[2]}", tokens[3:], env)
    if tokens[0] == "python" and len(tokens) > 1:
        if tokens[1] == "-c":
            return Command(line, "python -c", tokens[3:], env)
        return Command(line, f"python {tokens[1]}", tokens[2:], env)
    return Command(line, tokens[0], tokens[1:], env)


def doc_commands() -> list[Command]:
    return [
        c for doc in CURRENT for b in bash_blocks(doc) for line in bash_lines(b) for c in parse_commands(line)
    ]


# --- what a program accepts ----------------------------------------------------------------------


class _ParsedError(Exception):
    def __init__(self, parser):
        self.parser = parser


@functools.cache
def argparse_parser(program: str):
    """The parser an argparse program builds, caught at its ``parse_args`` (the program does not run)."""
    import argparse

    def capture(self, *args, **kwargs):
        raise _ParsedError(self)

    real = argparse.ArgumentParser.parse_args, argparse.ArgumentParser.parse_known_args
    argparse.ArgumentParser.parse_args = argparse.ArgumentParser.parse_known_args = capture
    saved_argv, saved_path = sys.argv, list(sys.path)
    sys.argv = [program]
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            if program in CONSOLE_SCRIPTS:
                (ep,) = [
                    e for e in importlib.metadata.entry_points(group="console_scripts") if e.name == program
                ]
                ep.load()()
            elif program.startswith("python -m "):
                runpy.run_module(program.split()[2], run_name="__main__", alter_sys=True)
            else:
                runpy.run_path(str(REPO / program.split()[1]), run_name="__main__")
    except _ParsedError as caught:
        return caught.parser
    finally:
        argparse.ArgumentParser.parse_args, argparse.ArgumentParser.parse_known_args = real
        sys.argv, sys.path[:] = saved_argv, saved_path
    raise AssertionError(f"{program} finished without parsing its arguments")


@functools.cache
def draccus_flags(program: str, types: tuple[tuple[str, str], ...]) -> frozenset[str]:
    """The options in a draccus program's help, scoped to ``--X.type`` choices, plus its ``--X.path``s."""
    from lerobot.configs.parser import print_scoped_help

    import lerobot_formation.plugin  # noqa: F401  (registers --env.type=formation, --policy.type=...)

    (ep,) = [e for e in importlib.metadata.entry_points(group="console_scripts") if e.name == program]
    fn = inspect.unwrap(getattr(sys.modules[ep.load().__module__], CONSOLE_SCRIPTS[program]))
    spec = inspect.getfullargspec(fn)
    config_class = spec.annotations[spec.args[0]]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        print_scoped_help(config_class, [f"--{k}.type={v}" for k, v in types])
    flags = set(re.findall(r"(?<![\w-])--[A-Za-z][\w.-]*", out.getvalue()))
    if hasattr(config_class, "__get_path_fields__"):
        flags |= {f"--{f}.path" for f in config_class.__get_path_fields__()}
    return frozenset(flags)


def check_command(cmd: Command) -> list[str]:
    """Problems of one command (empty: its program exists and takes every flag it is given)."""
    import argparse

    program, args = cmd.program, cmd.args
    if program == "scripts/run.sh":
        sub = args[0] if args else ""
        if sub not in RUN_SH or not os.access(REPO / program, os.X_OK):
            return [f"scripts/run.sh has no subcommand {sub!r} (or is not executable)"]
        if RUN_SH[sub] is None:
            return []
        program, args = RUN_SH[sub], args[1:]
    if program == "python -c":
        return []
    if program in CONSOLE_SCRIPTS and not (BIN / program).exists():
        return [f"no console script {BIN / program}"]
    if program.startswith("python -m ") and importlib.util.find_spec(program.split()[2]) is None:
        return [f"no module {program.split()[2]}"]
    if program.startswith("python ") and not program.startswith("python -m "):
        path = REPO / program.split()[1]
        if not path.is_file():
            return [f"no file {program.split()[1]}"]
        if "argparse" not in path.read_text():
            return [f"{program} takes no options, given {cmd.flags()}"] if cmd.flags() else []
    if program not in CONSOLE_SCRIPTS and not program.startswith("python "):
        # other tools (export, mkdir, sbatch, a scheduler's loop) are the shell's, not ours to check
        return [f"unknown program {program!r}"] if program.startswith("lerobot") else []
    if CONSOLE_SCRIPTS.get(program):
        types = dict(DRACCUS_DEFAULT_TYPES)
        types.update({f[2:-5]: cmd.value(f) for f in cmd.flags() if f.endswith(".type")})
        accepted = draccus_flags(program, tuple(sorted(types.items())))
        return [f"{program} does not take {f}" for f in cmd.flags() if f not in accepted]
    parser = argparse_parser(program)
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            argparse.ArgumentParser.parse_args(parser, args)
    except SystemExit:
        return [f"{program} rejects {args}: {err.getvalue().strip().splitlines()[-1]}"]
    return []


# --- fast tests ----------------------------------------------------------------------------------

COMMANDS = doc_commands()


def test_the_docs_have_their_commands():
    assert {p.name for p in DOCS} >= {"README.md", "usage.md", "results.md", "log.md", "setup.md"}
    programs = {c.program for c in COMMANDS}
    assert {
        "lerobot-formation-generate",
        "lerobot-train",
        "lerobot-eval",
        "lerobot-formation-bench",
    } <= programs


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_every_bash_block_parses(doc):
    fences = [line for line in doc.read_text().splitlines() if line.startswith("```")]
    assert len(fences) % 2 == 0, f"{doc.name}: an unclosed ``` fence"
    for block in bash_blocks(doc):
        proc = subprocess.run(["bash", "-n"], input=block, capture_output=True, text=True, timeout=30)
        assert proc.returncode == 0, f"{doc.name}: {proc.stderr}\n{block}"


@pytest.mark.parametrize("cmd", COMMANDS, ids=[str(c) for c in COMMANDS])
def test_a_command_exists_and_takes_its_flags(cmd):
    assert not check_command(cmd), check_command(cmd)


def test_the_flag_check_catches_what_a_program_refuses():
    for line in (
        "lerobot-formation-bench --controllers pac --scenes random:2 --no-such-flag 1",
        "lerobot-formation-generate --episodes many",
        "lerobot-eval --policy.path=x --env.type=formation --env.no_such_field=1",
        "python -m lerobot_formation.no_such_module",
        "python benchmarks/no_such_bench.py",
    ):
        (cmd,) = parse_commands(line)
        assert check_command(cmd), line


# what the repository holds at its root, not what running it writes there (.gitignore's folders)
WRITTEN_BY_RUNS = {"outputs", "data", "logs", "hub_folder"}
TOP_LEVEL = {
    p.name
    for p in REPO.iterdir()
    if (not p.name.startswith(".") or p.name == ".ci") and p.name not in WRITTEN_BY_RUNS
}
SUBPACKAGES = {
    p.name for p in (REPO / "lerobot_formation").iterdir() if p.is_dir() and p.name != "__pycache__"
}
PATHLIKE = re.compile(r"^\.?[\w.-]+(/[\w.*<>-]+)*/?$")
# a gymnasium env id (gym_formation/FormationNav-v0), not a path
GYM_ID = re.compile(r"^[\w.]+/[A-Z]\w*-v\d+$")


def mentioned_paths(doc: Path) -> set[str]:
    """Repository paths a doc mentions: backticked spans, link targets and command words."""
    text = doc.read_text()
    words = set(re.findall(r"`([^`\s]+)`", FENCE.sub("", text)))
    words |= {m for m in re.findall(r"\]\(([^)#\s]+)", text) if "://" not in m}
    for block in bash_blocks(doc):
        for line in bash_lines(block):
            words |= {w.split("=", 1)[-1] for w in _tokens(line)}
    paths = set()
    for word in words:
        word = word.strip("'\",;:")
        if not PATHLIKE.match(word) or "<" in word or "*" in word or GYM_ID.match(word):
            continue
        first = word.split("/")[0]
        # a subpackage path names a module file ("data/x" may as well be a dataset folder at the root)
        if first in TOP_LEVEL and "/" in word or first in SUBPACKAGES and word.endswith(".py"):
            paths.add(word)
        elif re.fullmatch(r"[\w-]+\.py", word):
            paths.add(word)
    return paths


@functools.cache
def repository_names() -> frozenset[str]:
    """The names of every file and folder in the repository but under .venv/ and outputs/ (walked
    once: a walk per mentioned name would walk the virtual environment's many files each time)."""
    names = set()
    for _, dirs, files in os.walk(REPO):
        dirs[:] = [d for d in dirs if d not in (".venv", "outputs")]
        names.update(dirs)
        names.update(files)
    return frozenset(names)


def path_problem(doc: Path, path: str) -> str | None:
    if "/" not in path:  # a bare module file name: somewhere in the package or the scripts
        found = path in repository_names()
        return None if found else f"{doc.name}: no file named {path} in the repository"
    for base in (doc.parent, REPO, REPO / "lerobot_formation"):
        if (base / path).exists():
            return None
    relative = os.path.relpath(doc.parent / path, REPO) if not (REPO / path).exists() else path
    if relative in WRITTEN_ELSEWHERE or path in WRITTEN_ELSEWHERE:
        return None
    return f"{doc.name}: {path} does not exist"


@pytest.mark.parametrize("doc", CURRENT, ids=lambda p: p.name)
def test_every_repository_path_a_doc_mentions_exists(doc):
    problems = [p for p in (path_problem(doc, path) for path in sorted(mentioned_paths(doc))) if p]
    assert not problems, "\n".join(problems)


def test_the_path_check_catches_a_moved_module(tmp_path):
    doc = REPO / "docs" / "usage.md"
    assert path_problem(doc, "lerobot_formation/no_such_module.py")
    assert path_problem(doc, "core/no_such_file.py")
    assert path_problem(doc, "no_such_file.py")
    assert path_problem(doc, "log.md") is None and path_problem(doc, "core/world/scenes.py") is None


def test_what_the_commands_write_at_the_root_is_git_ignored():
    if not (REPO / ".git").exists():
        pytest.skip("not a git checkout")
    written = {
        cmd.value(flag).split("/")[0]
        for cmd in COMMANDS
        for flag in WRITE_FLAGS
        if cmd.value(flag) and not cmd.value(flag).startswith(("/", "$"))
    }
    assert {"data", "outputs", "hub_folder"} <= written
    for top in sorted(written):
        proc = subprocess.run(["git", "check-ignore", "-q", f"{top}/x"], cwd=REPO, timeout=30)
        assert proc.returncode == 0, f"{top}/ (written by a documented command) is not git-ignored"


# --- end to end ----------------------------------------------------------------------------------

# The README's shortest path for each job: its bash block that generates a dataset.
(JOURNEYS,) = [b for b in bash_blocks(REPO / "README.md") if "lerobot-formation-generate" in b]
SCALE = [  # (pattern, replacement): each journey at a size that runs in seconds
    (r"--episodes \d+", "--episodes 3"),
    (r"--output_dir=outputs/train_route", "--output_dir=outputs/train_route --steps=2 --save_freq=2 --log_freq=1 --env_eval_freq=0 --batch_size=8"),
    (r"--eval\.n_episodes=\d+ --eval\.batch_size=\d+", "--eval.n_episodes=2 --eval.batch_size=2 --env.episode_length=30"),
    (r"level5:\d+", "level5:2"),
]  # fmt: skip


def scaled(block: str) -> list[str]:
    lines = bash_lines(block)
    for pattern, _ in SCALE:
        assert any(re.search(pattern, line) for line in lines), f"SCALE entry {pattern!r} matches no journey"
    out = []
    for line in lines:
        for pattern, replacement in SCALE:
            line = re.sub(pattern, replacement, line)
        out.append(line)
    return out


def _run(line: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {
        **os.environ,
        "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",
        "PYTHONPATH": str(REPO),
        "HF_HUB_OFFLINE": "1",
        "HF_DATASETS_OFFLINE": "1",
        "HF_LEROBOT_HOME": str(cwd / "hf_lerobot_home"),
        "OMP_NUM_THREADS": "1",
        "MPLBACKEND": "Agg",
    }
    return subprocess.run(
        ["bash", "-c", f"set -eo pipefail\n{line}"],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )


def test_the_readme_dataset_journey_runs_scaled_down(tmp_path):
    (line,) = [c for c in scaled(JOURNEYS) if c.startswith("lerobot-formation-generate")]
    proc = _run(line, tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "data/formation_wide_route/meta/info.json").is_file()
    assert "Traceback" not in proc.stderr and proc.stdout.startswith("episodes 3, frames ")


@pytest.mark.slow
def test_the_readme_journeys_run_end_to_end_scaled_down(tmp_path):
    for name in ("configs", "pretrained"):
        (tmp_path / name).symlink_to(REPO / name)
    for line in scaled(JOURNEYS):
        proc = _run(line, tmp_path)
        assert proc.returncode == 0, f"{line}\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"
        assert "Traceback" not in proc.stderr, f"{line}\n{proc.stderr[-4000:]}"
    assert (tmp_path / "outputs/train_route/checkpoints/last/pretrained_model/model.safetensors").is_file()
    assert len((tmp_path / "outputs/eval_default/metrics.jsonl").read_text().splitlines()) >= 2
    assert (tmp_path / "outputs/bench/results.json").is_file() and (
        tmp_path / "outputs/bench/tables.md"
    ).is_file()
