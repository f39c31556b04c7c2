"""Results artifacts: a bench run's ``results.json`` reduced to what a published table needs.

The published tables of the README and docs/ are written from small JSON files in ``results/``
(``scripts/publish_tables.py``), never typed by hand. One artifact is one bench run (or one merged
sharded run), reduced by ``reduce_results``::

    {"format": "lerobot-formation-results", "version": 1,
     "command": "lerobot-formation-bench --controllers pac,... --scenes level5:500 ...",
     "date": "YYYY-MM-DD", "host": "Linux x86_64, 2 cores (...)", "device": "cpu",
     "policy_path": "pretrained/...", "candidates": 10, "main": "level5",
     "sets": {"level5": {"spec": "level5:500", "seed": 1000000, "conditions": {...},
                         "controllers": {"pac": {"n": 500, "successes": 271, "collisions": 189,
                                                 "timeouts": 40, "struck_by_mover": 116,
                                                 "smoothness": 1.56, "jerk": 4.39,
                                                 "outcomes": "sctss..."}}}}}

Per controller: the episode count, the counts of successes, collisions and timeouts (and of the
collisions a mover struck, where the run counted them), the means over successful episodes of
``control_smoothness`` and ``jerk`` (null where no episode succeeded), and ``outcomes``, one letter per
episode in scene-index order (``s`` success, ``c`` collision, ``t`` timeout), so two artifacts on the
same scenes can be compared episode by episode; the oracle's entry also has ``unsolved``, the cause of
each scene it left by scene index (``core.episodes.oracle.CAUSES``). Rates and intervals are not stored: the publisher
computes them from the counts.
"""

from __future__ import annotations

import json
import os
import platform
import shlex
import sys
from pathlib import Path

from lerobot_formation.core.episodes.oracle import ORACLE_KEY, SOLVED

FORMAT = "lerobot-formation-results"
VERSION = 1
OUTCOME_LETTERS = {"success": "s", "collision": "c", "timeout": "t"}
# the bench's summary keys of the two motion means a table may show (means over successful episodes)
MEANS = {"smoothness": "control_smoothness", "jerk": "jerk"}
# what the console scripts are called, by the module file a ``python -m`` run names in sys.argv[0]
PROGRAMS = {"cli.py": "lerobot-formation-bench", "merge.py": "lerobot-formation-bench-merge"}


def host_description() -> str:
    """This machine in a few words: OS, architecture, CPU cores and the CPU's model name where Linux
    names it, e.g. ``Linux x86_64, 2 cores (Intel(R) Xeon(R) CPU @ 2.20GHz)``."""
    text = f"{platform.system()} {platform.machine()}, {os.cpu_count()} cores"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return f"{text} ({line.split(':', 1)[1].strip()})"
    except OSError:
        pass
    return text


def bench_command(argv: list[str] | None = None) -> str | None:
    """The command line of this process as a user types it (``lerobot-formation-bench ARGS``), or None
    when the process is not one of the bench's programs (a test calling ``main(argv)``)."""
    argv = sys.argv if argv is None else argv
    if not argv:
        return None
    path = Path(argv[0])
    if path.name.startswith("lerobot-formation-bench"):
        program = path.name
    elif path.parent.name == "bench" and path.name in PROGRAMS:  # python -m lerobot_formation.bench.cli
        program = PROGRAMS[path.name]
    else:
        return None
    return shlex.join([program, *argv[1:]])


def _controller(entry: dict) -> dict:
    n = int(entry["n_episodes"])
    episodes = entry.get("episodes")
    if episodes is not None:
        ordered = sorted(episodes, key=lambda e: e["scene_index"])
        outcomes = "".join(OUTCOME_LETTERS.get(e["outcome"], "?") for e in ordered)
        successes = outcomes.count("s")
    else:
        outcomes = None
        successes = round((entry.get("success_rate") or 0.0) * n)
    out = {
        "n": n,
        "successes": successes,
        "collisions": int(entry["collisions"]),
        "timeouts": int(entry["timeouts"]),
    }
    if entry.get("struck_by_mover") is not None:
        out["struck_by_mover"] = int(entry["struck_by_mover"])
    for key, name in MEANS.items():
        value = entry.get(name)
        out[key] = value.get("mean") if isinstance(value, dict) else None
    if outcomes is not None:
        out["outcomes"] = outcomes
        causes = {
            str(e["scene_index"]): e[ORACLE_KEY] for e in ordered if e.get(ORACLE_KEY, SOLVED) != SOLVED
        }
        if any(ORACLE_KEY in e for e in ordered):  # the oracle's: why it left each scene it left
            out["unsolved"] = causes
    return out


def reduce_results(
    payload: dict, command: str | None = None, host: str | None = None, outcomes: bool = True
) -> dict:
    """The artifact of a bench ``results.json`` (``payload``, as read with ``json.loads``).

    ``command``: the command line that made the run (default: the one the bench recorded,
    ``meta.command``); ``host``: where it ran (default: ``meta.host``, else this machine's
    ``host_description``, for a run reduced where it ran). ``outcomes=False`` leaves the per-episode
    letters out. ValueError for an incomplete run, a payload that is no bench results, or a run
    without a recorded or given command."""
    meta = payload.get("meta") if isinstance(payload, dict) else None
    if not isinstance(meta, dict) or not isinstance(payload.get("by_scenes"), dict):
        raise ValueError("not a lerobot-formation-bench results.json (no meta or by_scenes)")
    if meta.get("incomplete"):
        raise ValueError(f"an incomplete run ({meta.get('error')}): rerun it before publishing it")
    if meta.get("shard"):
        raise ValueError(
            f"shard {meta['shard']} of a run: merge the shards first (lerobot-formation-bench-merge)"
        )
    command = command or meta.get("command")
    if not command:
        raise ValueError("the run recorded no command line: give the one that made it")
    specs = {"unseen": meta.get("unseen")}
    conditions = {"unseen": meta.get("unseen_conditions") or {}}
    sets = {}
    main = next((label for label in payload["by_scenes"] if label != "unseen"), None)
    for label, controllers in payload["by_scenes"].items():
        reduced = {name: _controller(entry) for name, entry in controllers.items()}
        if not outcomes:
            for entry in reduced.values():
                entry.pop("outcomes", None)
        sets[label] = {
            "spec": specs.get(label, meta.get("scenes")),
            "seed": meta.get("seed"),
            "conditions": conditions.get(label, meta.get("conditions") or {}),
            "controllers": reduced,
        }
    return {
        "format": FORMAT,
        "version": VERSION,
        "command": command,
        "date": meta.get("date"),
        "host": host or meta.get("host") or host_description(),
        "device": meta.get("device", "cpu"),
        "policy_path": meta.get("policy_path"),
        "candidates": meta.get("candidates"),
        "main": main,
        "sets": sets,
    }


def check_artifact(artifact: dict, where: str = "artifact") -> None:
    """ValueError naming ``where`` and the problem unless ``artifact`` is a well-formed artifact."""
    if not isinstance(artifact, dict) or artifact.get("format") != FORMAT:
        raise ValueError(f"{where}: not a results artifact (format {FORMAT!r})")
    if artifact.get("version") != VERSION:
        raise ValueError(f"{where}: version {artifact.get('version')!r}, this code reads {VERSION}")
    for key in ("command", "date", "host", "main", "sets"):
        if not artifact.get(key):
            raise ValueError(f"{where}: no {key!r}")
    for label, scene_set in artifact["sets"].items():
        for name, c in scene_set.get("controllers", {}).items():
            counts = [c.get(k) for k in ("n", "successes", "collisions", "timeouts")]
            if not all(isinstance(x, int) and x >= 0 for x in counts):
                raise ValueError(
                    f"{where}: {label}/{name}: n, successes, collisions, timeouts must be counts"
                )
            n, s, col, t = counts
            if s + col + t != n:
                raise ValueError(
                    f"{where}: {label}/{name}: successes + collisions + timeouts != n ({s}+{col}+{t} != {n})"
                )
            if "outcomes" in c and len(c["outcomes"]) != n:
                raise ValueError(f"{where}: {label}/{name}: {len(c['outcomes'])} outcome letters for n = {n}")


def read_artifact(path: Path) -> dict:
    """An artifact file, checked (``check_artifact``); ValueError naming the file otherwise."""
    path = Path(path)
    try:
        artifact = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: cannot be read as JSON: {e}") from e
    check_artifact(artifact, str(path))
    return artifact


def dump_artifact(artifact: dict) -> str:
    """An artifact as the text ``results/NAME.json`` holds (sorted keys, one controller a line or so)."""
    return json.dumps(artifact, indent=1, sort_keys=True) + "\n"
