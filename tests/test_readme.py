"""Every README command works as written (issue 13).

The README's ```bash blocks are parsed into commands (backslash continuations joined, ``for`` loops
expanded, ``VAR=value`` prefixes kept). The fast part checks, without running anything:

- every command runs a known program that exists (a console script of this environment, a file of
  the repository, an importable ``python -m`` module), and takes every ``--flag`` the README gives
  it: argparse programs are parsed by their own parser (names, types and choices), LeRobot's draccus
  programs are checked against their own help text, scoped to the formation env and policy;
- the same for the commands quoted inline in the prose (flag names only: they use placeholders such
  as ``K``), and a bare ``--flag`` in the prose must belong to one of the project's programs;
- a path a command reads exists in the repository or is written by an earlier README command (a
  ``checkpoints/NNNNNN`` folder must be one the earlier training run saves);
- the substitution table below leaves every command that the end-to-end test runs at a small size.

The end-to-end part (``slow``) runs the bash blocks in order in a temporary folder (``configs`` and
``pretrained`` linked in), with only the size flags rewritten by ``SCALE`` (episodes, steps,
n_episodes, scene counts), and checks that each command succeeds and creates what it names.
"""

from __future__ import annotations

import ast
import contextlib
import functools
import importlib.metadata
import importlib.util
import inspect
import io
import json
import os
import re
import runpy
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"
BIN = Path(sys.executable).parent

# --- what the tests know about the project's programs --------------------------------------------

CONSOLE_SCRIPTS = {  # console script -> draccus-wrapped function of its module (None: argparse)
    "lerobot-formation-generate": None,
    "lerobot-formation-bench": None,
    "lerobot-train": "train",
    "lerobot-eval": "eval_main",
    "lerobot-edit-dataset": "edit_dataset",
}
# ``--X.type`` values the draccus help is scoped to when a command does not give them (the project's
# configs and checkpoints are all of these types).
DRACCUS_DEFAULT_TYPES = {"policy": "formation_diffusion", "env": "formation"}
# scripts/run.sh subcommand -> the program it runs with the extra arguments (see scripts/run.sh).
RUN_SH = {"demo": "python -m lerobot_formation.bench.demo", "test": None, "setup": None}
SHELL_WORDS = {"wait", "source", "time"}  # not programs of the project: nothing to check

# Paths a command writes and reads (flags; ``env:VAR`` is a VAR=value prefix).
WRITES = {
    "lerobot-formation-generate": ["--root", "--push-to"],
    "lerobot-train": ["--output_dir"],
    "lerobot-eval": ["--output_dir", "--env.episode_metrics_path"],
    "lerobot-edit-dataset": ["--new_root"],
    "lerobot-formation-bench": ["--out"],
    "python -m datasets_scripts.dagger_scenes": ["--out"],
}
# Programs that refuse to write into an existing folder (unless --overwrite, the generator's).
REFUSE_EXISTING = {"lerobot-formation-generate", "lerobot-train", "lerobot-edit-dataset"}
READS = {
    "lerobot-formation-generate": ["--scenes"],
    "lerobot-train": ["--config_path", "--dataset.root", "--policy.path"],
    "lerobot-eval": ["--policy.path", "--env.scenes_file"],
    "lerobot-edit-dataset": ["--operation.roots"],
    "lerobot-formation-bench": ["--policy.path", "--dataset.root"],
    "python -m datasets_scripts.dagger_scenes": ["--policy.path"],
    "python -c": ["env:HF_LEROBOT_HOME"],
}

# --- the end-to-end run: the substitution table -------------------------------------------------

# program -> flag -> scaled value; a dict maps the README's value to the scaled one (a README value
# missing from it is an error: add it here).
SCALE = {
    "lerobot-formation-generate": {"--episodes": "4"},  # >= 1 per shard of the 4-shard loop
    "lerobot-train": {"--steps": "2"},
    "lerobot-eval": {"--eval.n_episodes": "1", "--eval.batch_size": "1"},
    "lerobot-formation-bench": {
        "--scenes": {"dataset:100": "dataset:1"},
        "--unseen": {"random:100": "random:1"},
    },
    "python -m datasets_scripts.dagger_scenes": {"--rollouts": "4"},
    "python -m lerobot_formation.policy.distill": {"--steps": "2", "--batch-size": "8"},
    "python benchmarks/bench_sampling_steps.py": {"--steps": "1"},
}
# Size flags a README command leaves at a large default: added after the program name.
ADD_IF_MISSING = {
    "lerobot-formation-generate": ["--episodes", "4"],
    "lerobot-train": ["--steps=2"],
    "python benchmarks/bench_sampling_steps.py": ["--scenes", "random:2", "--reference", "1"],
}
RESUMED_STEPS = "4"  # a resumed run (--resume=true) goes on from its 2 steps to this
# Paths that follow from the scaling: the last checkpoint of a --steps=2 run is 000002.
PATHS = {"checkpoints/032000/": "checkpoints/000002/"}
# Commands the end-to-end test does not run (a substring of the README line -> why); their flags and
# paths are still checked by the fast tests.
NOT_RUN = {
    "scripts/run.sh demo": "the demo itself: set-up plus 4 controllers on 70 scenes (minutes)",
    "scripts/run.sh test": "the test suite itself",
    "formation_diffusion_paper.json": "the paper-size network (U-Net 256-512-1024): minutes per step on a CPU",
    "accelerate launch --multi_gpu": "needs GPUs",
}
# repository folders the commands read, linked into the run folder
LINKED = ("configs", "pretrained", "benchmarks")


# --- parsing the README --------------------------------------------------------------------------


@dataclass
class Command:
    line: str  # the README's logical line (continuations joined)
    program: str  # "lerobot-train", "python -m X", "python scripts/x.py", "python -c", "scripts/run.sh"
    args: list[str]
    env: dict[str, str] = field(default_factory=dict)
    inline: bool = False  # quoted in the prose (placeholders allowed), not in a bash block

    def flags(self) -> list[str]:
        return [a.split("=", 1)[0] for a in self.args if a.startswith("--") and "*" not in a]

    def value(self, flag: str) -> str | None:
        for i, a in enumerate(self.args):
            if a.startswith(flag + "="):
                return a.split("=", 1)[1]
            if a == flag and i + 1 < len(self.args) and not self.args[i + 1].startswith("--"):
                return self.args[i + 1]
        return None

    def __str__(self) -> str:
        return self.line if len(self.line) < 90 else self.line[:87] + "..."


def readme_text() -> str:
    return README.read_text()


FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```", re.S | re.M)


def bash_lines(text: str) -> list[str]:
    """The logical lines of the ```bash blocks, in order (continuations joined, comment lines dropped)."""
    lines = []
    for m in FENCE.finditer(text):
        if m.group(1) != "bash":
            continue
        for line in re.sub(r"\s*\\\n\s*", " ", m.group(2)).splitlines():
            if line.strip() and not line.lstrip().startswith("#"):
                lines.append(line.strip())
    return lines


def _tokens(line: str) -> list[str]:
    line = re.sub(r"\$\(which ([\w.-]+)\)", r"\1", line)  # accelerate launch $(which lerobot-train)
    lexer = shlex.shlex(line, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    return list(lexer)


def _expand_loops(tokens: list[str]) -> list[str]:
    """``for V in a b; do BODY & done; wait`` -> BODY with $V=a ; BODY with $V=b ; wait."""
    if not tokens or tokens[0] != "for":
        return tokens
    var, i = tokens[1], tokens.index("do")
    values = tokens[3 : tokens.index(";")]
    j = len(tokens) - 1 - tokens[::-1].index("done")
    body = tokens[i + 1 : j]
    out = []
    for v in values:
        out += [t.replace(f"${var}", v) for t in body] + ([";"] if body[-1] not in ("&", ";") else [])
    return out + tokens[j + 1 :]


def parse_commands(line: str, inline: bool = False) -> list[Command]:
    """The commands of one shell line (split at ; & && || |)."""
    commands, current = [], []
    for tok in _expand_loops(_tokens(line)) + [";"]:
        if tok in (";", "&", "&&", "||", "|"):
            if current:
                commands.append(_command(line, current, inline))
            current = []
        else:
            current.append(tok)
    return [c for c in commands if c is not None]


def _command(line: str, tokens: list[str], inline: bool) -> Command | None:
    env = {}
    while tokens and re.fullmatch(r"[A-Z_][A-Z0-9_]*=\S*", tokens[0]):
        k, v = tokens.pop(0).split("=", 1)
        env[k] = v
    if not tokens or tokens[0] in SHELL_WORDS:
        return None
    if tokens[0] == "accelerate":  # accelerate launch [its options] PROGRAM args
        k = next(i for i, t in enumerate(tokens) if t in CONSOLE_SCRIPTS)
        tokens = tokens[k:]
    if tokens[0] == "python" and len(tokens) > 1:
        if tokens[1] in ("-m", "-c"):
            program = f"python {tokens[1]} {tokens[2]}" if tokens[1] == "-m" else "python -c"
            return Command(line, program, tokens[3:], env, inline)
        return Command(line, f"python {tokens[1]}", tokens[2:], env, inline)
    return Command(line, tokens[0], tokens[1:], env, inline)


def readme_commands(text: str | None = None) -> list[Command]:
    return [c for line in bash_lines(text or readme_text()) for c in parse_commands(line)]


def _prose(text: str) -> str:
    return FENCE.sub("", text)


def inline_spans(text: str | None = None) -> list[str]:
    return [
        m.group(1).replace("\n", " ").strip()
        for m in re.finditer(r"`([^`]+)`", _prose(text or readme_text()))
    ]


def _is_program_span(span: str) -> bool:
    words = [w for w in span.split() if not re.fullmatch(r"[A-Z_][A-Z0-9_]*=\S*", w)]
    if not words:
        return False
    if words[0] in CONSOLE_SCRIPTS or words[0] == "scripts/run.sh":
        return True
    return (
        words[0] == "python"
        and len(words) > 1
        and re.match(r"(scripts/|benchmarks/|-m$)", words[1]) is not None
    )


def inline_commands(text: str | None = None) -> list[Command]:
    return [c for s in inline_spans(text) if _is_program_span(s) for c in parse_commands(s, inline=True)]


def bare_flag_spans(text: str | None = None) -> list[str]:
    """Prose spans that are only options (``--episodes``, ``... --stock 100:sync --threads 1``)."""
    return [s for s in inline_spans(text) if re.match(r"(--|\.\.\. --)", s)]


# --- what a program accepts ----------------------------------------------------------------------


class _StopAtParseError(Exception):
    def __init__(self, parser):
        self.parser = parser


@contextlib.contextmanager
def _argv(argv: list[str]):
    saved_argv, saved_path = sys.argv, list(sys.path)
    sys.argv = argv
    try:
        yield
    finally:
        sys.argv, sys.path[:] = saved_argv, saved_path


def _run_until_parse(program: str):
    """Run an argparse program in this process up to its ``parse_args`` and return its parser."""
    import argparse

    def capture(self, *args, **kwargs):
        raise _StopAtParseError(self)

    real = argparse.ArgumentParser.parse_args, argparse.ArgumentParser.parse_known_args
    argparse.ArgumentParser.parse_args = argparse.ArgumentParser.parse_known_args = capture
    try:
        with _argv([program]), contextlib.redirect_stdout(io.StringIO()):
            if program in CONSOLE_SCRIPTS:
                _entry_point(program)()
            elif program.startswith("python -m "):
                runpy.run_module(program.split()[2], run_name="__main__", alter_sys=True)
            else:
                runpy.run_path(str(REPO / program.split()[1]), run_name="__main__")
    except _StopAtParseError as c:
        return c.parser
    finally:
        argparse.ArgumentParser.parse_args, argparse.ArgumentParser.parse_known_args = real
    raise AssertionError(f"{program} finished without parsing its arguments")


def _entry_point(name: str):
    (ep,) = [e for e in importlib.metadata.entry_points(group="console_scripts") if e.name == name]
    return ep.load()


def program_missing(program: str) -> str | None:
    """Why ``program`` does not exist, or None."""
    if program in CONSOLE_SCRIPTS:
        return None if (BIN / program).exists() else f"no console script {BIN / program}"
    if program == "scripts/run.sh":
        return None if os.access(REPO / program, os.X_OK) else "scripts/run.sh is not executable"
    if program.startswith("python -m "):
        module = program.split()[2]
        return None if importlib.util.find_spec(module) else f"no module {module}"
    if program == "python -c":
        return None
    if program.startswith("python "):
        path = program.split()[1]
        if not re.match(r"(scripts|benchmarks)/", path):
            return f"{path} is not a script of the project"
        return None if (REPO / path).is_file() else f"no file {path}"
    return f"unknown program {program!r}"


@functools.cache
def _argparse_parser(program: str):
    return _run_until_parse(program)


def _takes_options(program: str) -> bool:
    if program in CONSOLE_SCRIPTS or program.startswith("python -m "):
        return True
    return "argparse" in (REPO / program.split()[1]).read_text()


@functools.cache
def _draccus_flags(program: str, types: tuple[tuple[str, str], ...]) -> frozenset[str]:
    """The options of a draccus program's help text, scoped to ``--X.type`` choices, plus the
    ``--X.path`` of its path fields (LeRobot's own, not draccus')."""
    from lerobot.configs.parser import print_scoped_help

    import lerobot_formation.plugin  # noqa: F401 (registers --env.type=formation, --policy.type=...)

    fn = getattr(sys.modules[_entry_point(program).__module__], CONSOLE_SCRIPTS[program])
    wrapped = inspect.unwrap(fn)
    spec = inspect.getfullargspec(wrapped)
    config_class = spec.annotations[spec.args[0]]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        print_scoped_help(config_class, [f"--{k}.type={v}" for k, v in types])
    flags = set(re.findall(r"(?<![\w-])--[A-Za-z][\w.-]*", out.getvalue()))
    if hasattr(config_class, "__get_path_fields__"):
        flags |= {f"--{f}.path" for f in config_class.__get_path_fields__()}
    return frozenset(flags)


def _draccus_types(cmd: Command) -> tuple[tuple[str, str], ...]:
    types = {k: v for k, v in DRACCUS_DEFAULT_TYPES.items()}
    for flag in cmd.flags():
        if flag.endswith(".type"):
            types[flag[2:-5]] = cmd.value(flag)
    return tuple(sorted(types.items()))


def check_command(cmd: Command) -> list[str]:
    """Problems of one README command (empty: it exists and takes every flag it is given)."""
    missing = program_missing(cmd.program)
    if missing:
        return [missing]
    program, args = cmd.program, cmd.args
    if program == "scripts/run.sh":
        usage = re.search(r"usage: scripts/run.sh \{([\w|]+)\}", (REPO / program).read_text())
        sub = args[0] if args else ""
        if not usage or sub not in usage.group(1).split("|") or sub not in RUN_SH:
            return [f"scripts/run.sh has no subcommand {sub!r}"]
        if RUN_SH[sub] is None:
            return []
        program, args = RUN_SH[sub], args[1:]
    if program == "python -c":
        return []
    cmd = Command(cmd.line, program, args, cmd.env, cmd.inline)
    if program in CONSOLE_SCRIPTS and CONSOLE_SCRIPTS[program]:
        accepted = _draccus_flags(program, _draccus_types(cmd))
        return [f"{program} does not take {f}" for f in cmd.flags() if f not in accepted]
    if not _takes_options(program):
        return [f"{program} takes no options, the README gives it {cmd.flags()}"] if cmd.flags() else []
    parser = _argparse_parser(program)
    accepted = set(parser._option_string_actions)
    problems = [f"{program} does not take {f}" for f in cmd.flags() if f not in accepted]
    if not problems and not cmd.inline:  # the whole command line through the program's own parser
        import argparse

        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err):
                argparse.ArgumentParser.parse_args(parser, args)
        except SystemExit:
            problems.append(f"{program} rejects {args}: {err.getvalue().strip().splitlines()[-1]}")
    controllers = cmd.value("--controllers")
    if controllers and program in ("lerobot-formation-bench", "python -m lerobot_formation.bench.demo"):
        from lerobot_formation.bench.controllers import CONTROLLERS

        problems += [f"unknown controller {c!r}" for c in controllers.split(",") if c not in CONTROLLERS]
    return problems


# --- the fast tests ------------------------------------------------------------------------------

COMMANDS = readme_commands()
INLINE = inline_commands()


def test_the_readme_has_its_commands():
    programs = {c.program for c in COMMANDS}
    assert {
        "lerobot-formation-generate",
        "lerobot-train",
        "lerobot-eval",
        "lerobot-formation-bench",
    } <= programs
    assert len(COMMANDS) >= 15 and len(INLINE) >= 10


@pytest.mark.parametrize("cmd", COMMANDS + INLINE, ids=[str(c) for c in COMMANDS + INLINE])
def test_a_readme_command_exists_and_takes_its_flags(cmd):
    assert not check_command(cmd), f"README: `{cmd.line}`: {check_command(cmd)}"


def test_the_flag_check_catches_what_a_program_refuses():
    bad = [
        "lerobot-train --config_path=configs/formation_diffusion_cpu.json --policy.no_such_field=1",
        "lerobot-eval --policy.path=pretrained/formation_diffusion_safe --env.no_such_field=1",
        "lerobot-formation-generate --episodes 2 --no-such-flag",
        "lerobot-formation-generate --scene-preset no_such_preset",  # a choice, checked by argparse
        "lerobot-formation-bench --controllers pac,no_such_controller",
        "python benchmarks/no_such_benchmark.py",
        "python -m datasets_scripts.no_such_module",
        "scripts/run.sh no_such_job",
        "lerobot-no-such-program --x",
    ]
    for line in bad:
        (cmd,) = parse_commands(line)
        assert check_command(cmd), f"not caught: {line}"


def test_every_option_named_in_the_prose_belongs_to_a_program():
    programs = {c.program for c in COMMANDS + INLINE} - {"scripts/run.sh", "python -c"}
    accepted = set()
    for p in programs:
        if p in CONSOLE_SCRIPTS and CONSOLE_SCRIPTS[p]:
            accepted |= _draccus_flags(p, tuple(sorted(DRACCUS_DEFAULT_TYPES.items())))
        elif _takes_options(p):
            accepted |= set(_argparse_parser(p)._option_string_actions)
    unknown = [
        (span, flag)
        for span in bare_flag_spans()
        for flag in Command(span, "", _tokens(span.removeprefix("..."))).flags()
        if flag not in accepted
    ]
    assert not unknown, f"options named in the README that no program takes: {unknown}"


def _paths(cmd: Command, flags: list[str]) -> list[str]:
    out = []
    for flag in flags:
        value = cmd.env.get(flag[4:]) if flag.startswith("env:") else cmd.value(flag)
        if value is None:
            continue
        out += ast.literal_eval(value) if value.startswith("[") else [value]
    return out


def _saved_steps(train: Command) -> set[int]:
    """The checkpoint steps a lerobot-train command saves (its flags over its --config_path JSON)."""
    config = {}
    if train.value("--config_path") and (REPO / train.value("--config_path")).is_file():
        config = json.loads((REPO / train.value("--config_path")).read_text())
    steps = int(train.value("--steps") or config.get("steps", 100_000))
    every = int(train.value("--save_freq") or config.get("save_freq", 20_000))
    return set(range(every, steps + 1, every)) | {steps}


def path_problems(commands: list[Command]) -> list[str]:
    """Read paths that neither exist in the repository nor are written by an earlier command, and
    writes into a folder an earlier command made by a program that refuses an existing one."""
    written: dict[str, Command] = {}
    problems = []
    for cmd in commands:
        for path in _paths(cmd, READS.get(cmd.program, [])):
            if path.split("/")[0] in LINKED and (REPO / path).exists():  # not outputs/, data/ of this clone
                continue
            parent = next((w for w in written if path == w or path.startswith(w.rstrip("/") + "/")), None)
            if parent is None:
                problems.append(f"`{cmd}` reads {path}, which no earlier README command writes")
                continue
            step = re.match(re.escape(parent.rstrip("/")) + r"/checkpoints/(\d+)(/|$)", path)
            if step and written[parent].program == "lerobot-train":
                if int(step.group(1)) not in _saved_steps(written[parent]):
                    problems.append(f"`{cmd}` reads {path}, a checkpoint `{written[parent]}` does not save")
        for path in _paths(cmd, WRITES.get(cmd.program, [])):
            if path in written and cmd.program in REFUSE_EXISTING and "--overwrite" not in cmd.flags():
                problems.append(
                    f"`{cmd}` writes {path}, which `{written[path]}` made (it refuses an existing one)"
                )
            written[path] = cmd
    return problems


def test_every_path_a_readme_command_reads_is_made_by_an_earlier_one_and_none_is_clobbered():
    assert not path_problems(COMMANDS), "\n".join(path_problems(COMMANDS))


def test_the_path_check_catches_a_path_nobody_writes():
    cmds = readme_commands(
        "```bash\nlerobot-formation-generate --root data/a\n"
        "lerobot-train --config_path=configs/formation_diffusion_cpu.json --dataset.root=data/b "
        "--output_dir=outputs/t\nlerobot-eval --policy.path=outputs/t/checkpoints/012345/pretrained_model\n"
        "lerobot-formation-generate --root data/a --push-to hub\n"
        "lerobot-formation-generate --root data/a --overwrite\n```\n"
    )
    problems = path_problems(cmds)
    assert len(problems) == 3, problems
    assert "data/b" in problems[0] and "012345" in problems[1] and "--push-to hub" in problems[2], problems


# --- the end-to-end run --------------------------------------------------------------------------


def scaled(line: str, previous: dict[str, str]) -> str:
    """The README line with its size flags rewritten (SCALE, ADD_IF_MISSING, PATHS); ``previous``
    holds the last scaled line of each program, for a ``PROGRAM ...`` placeholder line."""
    cmds = parse_commands(line)
    programs = {c.program for c in cmds}
    assert len(programs) == 1, f"one program per line, got {programs} in {line}"
    (program,) = programs
    out = line
    if f"{program} ..." in out:  # "lerobot-eval ... --env.scenes_file=X": the previous one's arguments
        assert program in previous, f"`{line}`: no earlier {program} command for its '...'"
        out = out.replace(f"{program} ...", previous[program])
    for flag, value in SCALE.get(program, {}).items():

        def sub(m, flag=flag, value=value):
            if isinstance(value, dict):
                assert m.group(3) in value, f"`{line}`: add {flag} {m.group(3)} to SCALE"
                return m.group(1) + m.group(2) + value[m.group(3)]
            return m.group(1) + m.group(2) + value

        out = re.sub(rf"(?<!\S)({re.escape(flag)})([= ])(\S+)", sub, out)
    add = ADD_IF_MISSING.get(program)
    if add and not any(c.value(add[0].split("=")[0]) for c in cmds):
        out = re.sub(rf"(?<!\S){re.escape(program)}(?!\S)", f"{program} {' '.join(add)}", out)
    if program == "lerobot-train" and "--resume=true" in out:
        out = re.sub(r"--steps=\S+", f"--steps={RESUMED_STEPS}", out)
    for old, new in PATHS.items():
        out = out.replace(old, new)
    previous[program] = out
    return out


def runs(line: str) -> bool:
    return not any(key in line for key in NOT_RUN)


def test_the_substitution_table_fits_the_readme_and_keeps_every_run_small():
    lines = bash_lines(readme_text())
    assert all(any(key in line for line in lines) for key in NOT_RUN), (
        "a NOT_RUN entry matches no README line"
    )
    assert all(any(old in line for line in lines) for old in PATHS), "a PATHS entry matches no README line"
    previous: dict[str, str] = {}
    for line in filter(runs, lines):
        for cmd in parse_commands(scaled(line, previous)):
            if cmd.program == "lerobot-formation-generate":
                assert int(cmd.value("--episodes")) <= 4, cmd.line
            if cmd.program == "lerobot-train":
                assert int(cmd.value("--steps")) <= 4, cmd.line
            if cmd.program == "lerobot-eval":
                assert cmd.value("--eval.n_episodes") == "1", cmd.line
            if cmd.program == "lerobot-formation-bench":
                counts = re.findall(r":(\d+)", f"{cmd.value('--scenes')} {cmd.value('--unseen') or ''}")
                assert all(int(n) <= 4 for n in counts), cmd.line
            if cmd.program == "python -m lerobot_formation.policy.distill":
                assert int(cmd.value("--steps")) <= 4, cmd.line
            if cmd.program == "python benchmarks/bench_sampling_steps.py":
                assert cmd.value("--scenes") == "random:2" and cmd.value("--steps") == "1", cmd.line
            if "--rollouts" in cmd.flags():
                assert int(cmd.value("--rollouts")) <= 4, cmd.line


@pytest.mark.slow
def test_the_readme_commands_run_end_to_end_scaled_down(tmp_path):
    for name in LINKED:
        (tmp_path / name).symlink_to(REPO / name)
    env = {
        **os.environ,
        "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",
        "HF_HUB_OFFLINE": "1",
        "HF_DATASETS_OFFLINE": "1",
        "HF_LEROBOT_HOME": str(tmp_path / "hf_lerobot_home"),
        "OMP_NUM_THREADS": "1",
        "TOKENIZERS_PARALLELISM": "false",
        "MPLBACKEND": "Agg",
    }
    previous: dict[str, str] = {}
    log = []
    for line in filter(runs, bash_lines(readme_text())):
        command = scaled(line, previous)
        start = time.monotonic()
        proc = subprocess.run(
            ["bash", "-c", f"set -eo pipefail\n{command}"],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=900,
        )
        log.append(f"{time.monotonic() - start:6.1f} s  {command}")
        assert proc.returncode == 0, (
            f"README command failed ({proc.returncode}):\n  {line}\nrun as\n  {command}\n"
            f"{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"
        )
        for cmd in parse_commands(command):
            for path in _paths(cmd, WRITES.get(cmd.program, [])):
                assert (tmp_path / path).exists(), f"`{command}` did not create {path}"
            if cmd.program == "lerobot-train" and cmd.value("--resume") == "true":
                run = Path(cmd.value("--config_path")).parents[3]
                assert (tmp_path / run / "checkpoints" / f"{int(RESUMED_STEPS):06d}").is_dir(), command
    print("\n".join(log))
