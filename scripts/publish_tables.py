"""Write every published table of README.md and docs/*.md from the artifacts in results/.

    python scripts/publish_tables.py                      # rewrite every table from results/
    python scripts/publish_tables.py --check              # exit 1 if a table differs or does not parse
    python scripts/publish_tables.py --add level5 outputs/published/level5   # results.json -> results/level5.json
    python scripts/publish_tables.py --rerun headline     # rerun the commands of a table's artifacts

A published table sits between two markers, ``<!-- table:NAME -->`` and ``<!-- /table:NAME -->``, in
README.md or a page of docs/; what goes between them is written by this script and nothing else: the
table, then a "Measured on" line naming the artifacts' dates, hosts and files. ``results/tables.toml``
says what each table shows (its artifacts, its rows: controllers with display labels, its columns);
``results/NAME.json`` is one bench run reduced by ``lerobot_formation.bench.artifacts`` (counts, not
rates: success cells are computed here, percent with a Wilson 95 % interval, the lower end rounded
down and the upper end up).

``--check`` changes nothing. It exits 1, naming the file, the table and the first line that differs,
when a published table is not what its artifacts give, and when any markdown table in README.md or
docs/*.md does not parse (a row whose cell count is not its header's, a missing delimiter row). A
table whose artifacts are not in results/ yet is published empty (its cells "-" where only some are
missing) and reported as pending; ``--check`` accepts that.

``--add NAME FOLDER`` reduces FOLDER/results.json (a whole run, or a merged sharded one; give
``--command`` where the bench recorded none, e.g. for a merge) into results/NAME.json, then rewrites the
tables. ``--rerun NAME`` runs the recorded command of artifact NAME again (or of every artifact table
NAME reads) into a temporary folder, records the new artifact and rewrites the tables.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import shlex
import subprocess
import sys
import tempfile
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))  # run from a checkout without installing it

from lerobot_formation.bench.artifacts import dump_artifact, read_artifact, reduce_results  # noqa: E402
from lerobot_formation.core.episodes.metrics import wilson_interval  # noqa: E402

OPEN = re.compile(r"^<!-- table:([\w-]+) -->\s*$")
CLOSE = "<!-- /table:{} -->"
FENCE = re.compile(r"^\s*(```|~~~)")
DELIMITER_CELL = re.compile(r"^\s*:?-+:?\s*$")
VALUES = ("success", "outcomes", "n", "smoothness", "jerk", "of_solvable", "solvable", "causes", "misses")
CEILING_VALUES = ("of_solvable", "solvable", "causes", "misses")  # the values that need a ceiling artifact
# a row's controller that stands for every run: the scenes some controller of the set, or the
# ceiling's oracle, solved (value "solvable")
ANY_RUN = "*"
PENDING = "-"


class PublishError(ValueError):
    """Bad input: a spec, an artifact or a marker this script cannot use (exit code 2)."""


# --- the spec and the cells --------------------------------------------------------------------------


@dataclass
class Cell:
    artifact: str
    scene_set: str | None
    controller: str
    value: str
    ceiling: str | None = None  # the artifact of the oracle's run on the same scenes


@dataclass
class Table:
    name: str
    header: list[str]
    rows: list[tuple[str, list[Cell]]] = field(default_factory=list)

    def artifacts(self) -> list[str]:
        names = [name for _, cells in self.rows for c in cells for name in (c.artifact, c.ceiling) if name]
        return list(dict.fromkeys(names))


def read_spec(path: Path) -> dict[str, Table]:
    """The tables of ``results/tables.toml``. Each ``[tables.NAME]`` has ``rows`` (or ``rows_from``,
    another table's name) and ``columns`` (arrays of inline tables) and optional ``label`` (the first
    column's header), ``artifact`` and ``set``. A row names a ``controller`` and its ``label``; a column its ``header`` and ``value``
    (one of VALUES); ``artifact`` (a results/NAME.json) and ``set`` (a scene set of it, default its main
    one) come from the column, else the row, else the table."""
    try:
        spec = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise PublishError(f"{path}: {e}") from e
    tables = {}
    for name, t in spec.get("tables", {}).items():
        where = f"{path.name}: table {name}"
        if "rows_from" in t:
            t = {**t, "rows": spec["tables"].get(t["rows_from"], {}).get("rows")}
        if not t.get("rows") or not t.get("columns"):
            raise PublishError(f"{where}: needs rows (or rows_from a table that has them) and columns")
        table = Table(name, [t.get("label", "controller")] + [c["header"] for c in t["columns"]])
        for row in t["rows"]:
            cells = []
            for col in t["columns"]:
                value = col.get("value") or row.get("value") or t.get("value") or "success"
                if value not in VALUES:
                    raise PublishError(f"{where}: column {col['header']!r}: value {value!r} not in {VALUES}")
                artifact = col.get("artifact") or row.get("artifact") or t.get("artifact")
                controller = row.get("controller") or col.get("controller")
                if not artifact or not controller:
                    raise PublishError(f"{where}: row {row.get('label')!r} has no artifact or controller")
                scene_set = col.get("set") or row.get("set") or t.get("set")
                ceiling = col.get("ceiling") or row.get("ceiling") or t.get("ceiling")
                if value in CEILING_VALUES and not ceiling:
                    raise PublishError(
                        f"{where}: column {col['header']!r}: value {value!r} needs a ceiling artifact"
                    )
                cells.append(Cell(artifact, scene_set, controller, value, ceiling))
            table.rows.append((row["label"], cells))
        tables[name] = table
    return tables


def percent_interval(successes: int, n: int) -> str:
    """``98.8 [97, 100]``: the success percent and its Wilson 95 % interval in whole percents, the lower
    end rounded down and the upper end up (so the printed interval holds the computed one)."""
    lo, hi = wilson_interval(successes, n)
    return f"{100 * successes / n:.1f} [{math.floor(100 * lo + 1e-9)}, {math.ceil(100 * hi - 1e-9)}]"


def solved_by_some_run(controllers: dict[str, dict]) -> list[bool]:
    """Per scene of a set (scene-index order): some run of ``controllers`` (the oracle's among them)
    solved it. The oracle's search is a lower bound on what can be solved, so a scene another
    controller solved counts as solvable too."""
    letters = [c.get("outcomes") for c in controllers.values()]
    if not letters or any(x is None for x in letters) or len({len(x) for x in letters}) != 1:
        raise PublishError("the solvable scenes need every run's per-episode outcomes, on the same scenes")
    return [any(x[i] == "s" for x in letters) for i in range(len(letters[0]))]


def ceiling_text(c: dict | None, value: str, controllers: dict[str, dict]) -> str:
    """A cell of the values that read the set's solvable scenes (``solved_by_some_run``)."""
    solved = solved_by_some_run(controllers)
    k = sum(solved)
    if value == "solvable":
        return percent_interval(k, len(solved))
    if value == "of_solvable":
        successes = k if c is None else c["successes"]  # None: the solvable scenes themselves
        return f"{100 * successes / k:.1f}" if k else PENDING
    # "causes": the oracle's causes of the scenes no run solved; "misses": of those some controller solved
    left = {
        i: cause for i, cause in (c.get("unsolved") or {}).items() if solved[int(i)] == (value == "misses")
    }
    if not left:
        return "none"
    counts: dict[str, int] = {}
    for cause in left.values():
        counts[cause] = counts.get(cause, 0) + 1
    return "; ".join(f"{n} {cause}" for cause, n in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def cell_text(c: dict, value: str) -> str:
    if value == "success":
        return percent_interval(c["successes"], c["n"])
    if value == "outcomes":
        struck = c.get("struck_by_mover")
        collisions = f"{c['collisions']} ({struck} struck)" if struck else str(c["collisions"])
        return f"{collisions} / {c['timeouts']}"
    if value == "n":
        return str(c["n"])
    mean = c.get(value)
    return PENDING if mean is None else f"{mean:.3g}"


def _same_scenes(
    table: str, cell: Cell, artifact: dict, ceiling: dict, scene_set: str, results_dir: str
) -> dict:
    """The controllers of the ceiling artifact's run on the same scene set (spec and seed) as the cell's."""
    mine, theirs = artifact["sets"][scene_set], ceiling["sets"].get(scene_set)
    if theirs is None or (theirs["spec"], theirs["seed"]) != (mine["spec"], mine["seed"]):
        raise PublishError(
            f"table {table}: {results_dir}/{cell.ceiling}.json did not run the scenes of "
            f"{results_dir}/{cell.artifact}.json's set {scene_set!r} ({mine['spec']}, seed {mine['seed']})"
        )
    return theirs["controllers"]


def render(
    table: Table, artifacts: dict[str, dict], results_dir: str = "results"
) -> tuple[list[str], list[str]]:
    """The lines between a table's markers, and the names of its artifacts that are missing (pending).
    Empty lines when none of its artifacts exists."""
    missing = [a for a in table.artifacts() if a not in artifacts]
    if len(missing) == len(table.artifacts()):
        return [], missing
    lines = ["| " + " | ".join(table.header) + " |", "|" + "---|" * len(table.header)]
    for label, cells in table.rows:
        texts = []
        for cell in cells:
            artifact = artifacts.get(cell.artifact)
            if artifact is None:
                texts.append(PENDING)
                continue
            scene_set = cell.scene_set or artifact["main"]
            controllers = dict(artifact["sets"].get(scene_set, {}).get("controllers", {}))
            if cell.ceiling:
                ceiling = artifacts.get(cell.ceiling)
                if ceiling is None:
                    texts.append(PENDING)
                    continue
                controllers.update(_same_scenes(table.name, cell, artifact, ceiling, scene_set, results_dir))
            if cell.controller != ANY_RUN and cell.controller not in controllers:
                raise PublishError(
                    f"table {table.name}: {results_dir}/{cell.artifact}.json has no controller "
                    f"{cell.controller!r} in its scene set {scene_set!r} (it has {sorted(controllers)})"
                )
            entry = controllers.get(cell.controller)
            if cell.controller == ANY_RUN:  # the solvable scenes: their share, and all of them
                value = {"success": "solvable", "solvable": "solvable", "of_solvable": "of_solvable"}
                if cell.value not in value:
                    texts.append(PENDING)
                    continue
                texts.append(ceiling_text(None, value[cell.value], controllers))
            elif cell.value in CEILING_VALUES:
                texts.append(ceiling_text(entry, cell.value, controllers))
            else:
                texts.append(cell_text(entry, cell.value))
        lines.append("| " + " | ".join([label, *texts]) + " |")
    measured: dict[tuple[str, str], list[str]] = {}
    for name in table.artifacts():
        if name in artifacts:
            device = artifacts[name].get("device") or "cpu"
            key = (
                artifacts[name]["date"],
                artifacts[name]["host"] + ("" if device == "cpu" else f", the network on {device}"),
            )
            measured.setdefault(key, []).append(f"`{results_dir}/{name}.json`")
    parts = [f"{date} on {host}: {', '.join(files)}" for (date, host), files in sorted(measured.items())]
    line = "Measured on " + "; ".join(parts) + " (each file holds its command)."
    if missing:
        # named, not linked: the artifact does not exist yet
        line += " Pending (no artifact yet): " + ", ".join(missing) + "."
    return lines + ["", line], missing


# --- the markdown files ----------------------------------------------------------------------------


def published_files(root: Path) -> list[Path]:
    return [p for p in [root / "README.md", *sorted((root / "docs").glob("*.md"))] if p.is_file()]


def blocks(lines: list[str], where: str) -> list[tuple[str, int, int]]:
    """(name, first line after the open marker, line of the close marker) of each marked table."""
    found = []
    for i, line in enumerate(lines):
        m = OPEN.match(line)
        if not m:
            continue
        name = m.group(1)
        close = next((j for j in range(i + 1, len(lines)) if lines[j].strip() == CLOSE.format(name)), None)
        if close is None:
            raise PublishError(f"{where}:{i + 1}: <!-- table:{name} --> has no {CLOSE.format(name)}")
        found.append((name, i + 1, close))
    return found


def split_row(line: str) -> list[str]:
    """The cells of a markdown table row (GitHub's rule: split at unescaped pipes, outer pipes dropped)."""
    body = line.strip()
    body = body[1:] if body.startswith("|") else body
    body = body[:-1] if body.endswith("|") and not body.endswith("\\|") else body
    return re.split(r"(?<!\\)\|", body)


def table_problems(lines: list[str], where: str) -> list[str]:
    """Every markdown table outside code fences must have a delimiter row under its header and the
    header's cell count in every row. A table is a run of lines starting with ``|``."""
    problems, in_fence, i = [], False, 0
    while i < len(lines):
        if FENCE.match(lines[i]):
            in_fence = not in_fence
        if in_fence or not lines[i].lstrip().startswith("|"):
            i += 1
            continue
        start = i
        while i < len(lines) and lines[i].lstrip().startswith("|"):
            i += 1
        rows = lines[start:i]
        width = len(split_row(rows[0]))
        if len(rows) < 2 or not all(DELIMITER_CELL.match(c) for c in split_row(rows[1])):
            problems.append(f"{where}:{start + 2}: a table without a delimiter row (|---|) under its header")
            continue
        for k, row in enumerate(rows[1:], start=start + 2):
            cells = len(split_row(row))
            if cells != width:
                problems.append(f"{where}:{k}: a table row has {cells} cells, its header {width}")
                break
    return problems


# --- publishing ----------------------------------------------------------------------------------


def load_artifacts(results: Path, names: list[str]) -> dict[str, dict]:
    out = {}
    for name in names:
        path = results / f"{name}.json"
        if path.is_file():
            try:
                out[name] = read_artifact(path)
            except ValueError as e:
                raise PublishError(str(e)) from e
    return out


def publish(root: Path, check: bool) -> tuple[list[str], list[str]]:
    """Write (or with ``check`` compare) every marked table under ``root``. Returns the problems (a
    table that differs or does not parse) and the notes (pending artifacts)."""
    results = root / "results"
    tables = read_spec(results / "tables.toml")
    artifacts = load_artifacts(results, sorted({a for t in tables.values() for a in t.artifacts()}))
    problems, notes, seen = [], [], set()
    for path in published_files(root):
        where = str(path.relative_to(root))
        lines = path.read_text().splitlines()
        new = list(lines)
        for name, first, close in reversed(blocks(lines, where)):
            if name not in tables:
                raise PublishError(f"{where}:{first}: table {name!r} is not in results/tables.toml")
            seen.add(name)
            expected, missing = render(tables[name], artifacts)
            if missing:
                notes.append(
                    f"{where}: table {name}: pending, no " + ", ".join(f"results/{m}.json" for m in missing)
                )
            published = lines[first:close]
            if check and published != expected:
                k = next(
                    j
                    for j in range(max(len(published), len(expected)))
                    if published[j : j + 1] != expected[j : j + 1]
                )
                got = published[k] if k < len(published) else "(nothing)"
                want = expected[k] if k < len(expected) else "(nothing)"
                problems.append(
                    f"{where}:{first + k + 1}: table {name}: published {got!r}, the artifacts give {want!r}"
                )
            new[first:close] = expected
        problems += table_problems(lines if check else new, where)
        if not check and new != lines:
            path.write_text("\n".join(new) + "\n")
    unused = sorted(set(tables) - seen)
    if unused:
        problems.append(
            f"results/tables.toml: tables {unused} have no <!-- table:NAME --> marker in README.md or docs/"
        )
    return problems, notes


def add(root: Path, name: str, folder: Path, command: str | None) -> Path:
    """Reduce ``folder``/results.json into results/NAME.json."""
    if not re.fullmatch(r"[\w-]+", name):
        raise PublishError(f"an artifact name is letters, digits, '_' and '-', got {name!r}")
    try:
        payload = json.loads((folder / "results.json").read_text())
        artifact = reduce_results(payload, command=command)
    except (OSError, json.JSONDecodeError, ValueError) as e:
        raise PublishError(f"{folder}: {e}") from e
    out = root / "results" / f"{name}.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(dump_artifact(artifact))
    return out


def rerun(root: Path, name: str) -> list[Path]:
    """Run again the command of artifact ``name`` (or of every artifact table ``name`` reads) and record
    the new artifacts."""
    tables = read_spec(root / "results" / "tables.toml")
    names = tables[name].artifacts() if name in tables else [name]
    written = []
    for artifact_name in names:
        path = root / "results" / f"{artifact_name}.json"
        if not path.is_file():
            raise PublishError(f"no {path.relative_to(root)} to rerun (make it with --add first)")
        command = read_artifact(path)["command"]
        argv = shlex.split(command)
        if argv[0] != "lerobot-formation-bench" or "--out" not in argv:
            raise PublishError(
                f"{path.name}: can rerun only a lerobot-formation-bench command with --out, got {command!r}"
            )
        with tempfile.TemporaryDirectory(prefix="publish-rerun-") as tmp:
            i = argv.index("--out")
            argv[i + 1] = str(Path(tmp) / "run")
            program = Path(sys.executable).with_name(argv[0])
            print(f"[{artifact_name}] {command}", flush=True)
            proc = subprocess.run([str(program), *argv[1:]], cwd=root)
            if proc.returncode != 0:
                raise PublishError(f"{artifact_name}: the command failed (exit {proc.returncode}): {command}")
            written.append(add(root, artifact_name, Path(tmp) / "run", command))
    return written


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="publish_tables.py",
        description=__doc__.split("\n")[0],
        epilog="Markers: <!-- table:NAME --> ... <!-- /table:NAME -->; spec: results/tables.toml.",
    )
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument(
        "--check", action="store_true", help="change nothing; exit 1 on a difference or a broken table"
    )
    mode.add_argument(
        "--add", nargs=2, metavar=("NAME", "FOLDER"), help="reduce FOLDER/results.json into results/NAME.json"
    )
    mode.add_argument(
        "--rerun", metavar="NAME", help="rerun artifact NAME's command (or every artifact of table NAME)"
    )
    ap.add_argument(
        "--command", help="with --add: the command line that made the run (where the bench recorded none)"
    )
    ap.add_argument("--root", type=Path, default=REPO, help="the repository (README.md, docs/, results/)")
    args = ap.parse_args(argv)
    root = args.root.resolve()
    try:
        if args.add:
            print(f"wrote {add(root, args.add[0], Path(args.add[1]), args.command)}")
        elif args.rerun:
            for path in rerun(root, args.rerun):
                print(f"wrote {path}")
        problems, notes = publish(root, check=args.check)
    except PublishError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for note in notes:
        print(f"note: {note}")
    for problem in problems:
        print(problem, file=sys.stderr)
    if problems:
        print(
            f"{len(problems)} problem(s); run `python scripts/publish_tables.py` to rewrite the tables from results/",
            file=sys.stderr,
        )
        return 1
    if not args.check:
        print("tables written from results/")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
