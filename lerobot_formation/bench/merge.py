"""``lerobot-formation-bench-merge``: combine the shards of a sharded bench run into one run's results.

Each shard is the output folder of ``lerobot-formation-bench ... --shard I/N`` (its ``results.json``).
The merged ``results.json`` and ``tables.md`` are those of the same command run whole: per controller
and scene set, the episodes of all shards in scene-index order, and the summary recomputed from them
(``core.episodes.metrics.summarize``; the same numbers up to float rounding). ``wall_time_s`` is the sum over
the shards and the safety layer's counts are summed (rates recomputed). Figures are not merged (run the
figures on the whole set, or look at each shard's own).

Refused, with one line ``error: ...`` and exit code 2: shards of different settings (controllers,
scene sets, seed, policy, candidates, inference steps, conditions), of different shard counts, a
shard given twice, a missing shard, an incomplete shard, or episodes whose indices do not make up
the whole set exactly once.

    lerobot-formation-bench-merge outputs/shard0 outputs/shard1 outputs/shard2 --out outputs/merged
    python -m lerobot_formation.bench.merge outputs/shard* --out outputs/merged
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from lerobot_formation.bench.controllers import controller_names, needs_policy
from lerobot_formation.bench.results import collisions_text, existing_run, safety_rates, write_results
from lerobot_formation.bench.settings import RUN_SETTINGS as SETTINGS
from lerobot_formation.bench.settings import BenchSettings, ControllerOptions
from lerobot_formation.core.episodes.metrics import FLAG_KEYS, METRIC_KEYS, STRUCK_KEY, summarize
from lerobot_formation.core.perception.conditions import Conditions
from lerobot_formation.core.world.sampling import SamplingReport


def read_shard(folder: Path) -> dict:
    """A shard's results.json; ValueError naming the folder if it is missing, broken or not a shard."""
    path = Path(folder) / "results.json"
    try:
        payload = json.loads(path.read_text())
    except FileNotFoundError as e:
        raise ValueError(f"{folder}: no results.json (not a bench output folder)") from e
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path} cannot be read as JSON: {e}") from e
    meta = payload.get("meta") if isinstance(payload, dict) else None
    if not isinstance(meta, dict) or "by_scenes" not in payload:
        raise ValueError(f"{path} is not a lerobot-formation-bench results.json (no meta or by_scenes)")
    if meta.get("incomplete"):
        raise ValueError(f"{path} is an incomplete run ({meta.get('error')}); rerun that shard")
    if not meta.get("shard"):
        raise ValueError(f"{path} is not a shard (run with --shard I/N)")
    return payload


def _merge_entries(entries: list[dict], where: str) -> dict:
    """One controller's entry from its shard entries: episodes by index, summary recomputed."""
    episodes = sorted((e for entry in entries for e in entry["episodes"]), key=lambda e: e["scene_index"])
    index = np.array([e["scene_index"] for e in episodes])
    if len(np.unique(index)) != len(index):
        raise ValueError(f"{where}: scene indices appear in more than one shard (overlapping shards)")
    if len(index) and not np.array_equal(index, np.arange(len(index))):
        missing = sorted(set(range(int(index.max()) + 1)) - set(index.tolist()))
        raise ValueError(f"{where}: scene indices {missing[:10]} are in no shard (a shard is missing)")
    keys = [k for k in episodes[0] if k in METRIC_KEYS] if episodes else list(METRIC_KEYS)  # run's order
    per = {
        key: np.array([np.nan if e.get(key) is None else e[key] for e in episodes], dtype=np.float64)
        for key in keys
    }
    per.update({flag: np.array([e["outcome"] == flag for e in episodes], dtype=bool) for flag in FLAG_KEYS})
    if episodes and STRUCK_KEY in episodes[0]:  # shards written before the flag existed have none
        per[STRUCK_KEY] = np.array([bool(e.get(STRUCK_KEY)) for e in episodes], dtype=bool)
    merged = summarize(per)
    merged["episodes"] = episodes
    merged["wall_time_s"] = float(sum(entry.get("wall_time_s", 0.0) for entry in entries))
    if any("safety" in entry for entry in entries):
        counts = [entry["safety"] for entry in entries if "safety" in entry]
        # the union of the counts: a shard written before a count existed adds 0 to it
        keys = dict.fromkeys(k for c in counts for k in c if not k.endswith("_rate"))
        stats = {k: sum(c.get(k, 0) for c in counts) for k in keys}
        merged["safety"] = {**stats, **safety_rates(stats)}
    merged["scenes"] = entries[0]["scenes"]
    if any("figures" in entry for entry in entries):  # a shard's figures show its scenes only
        merged["figures"] = []
    return merged


def merge_shards(payloads: list[dict], names: list[str] | None = None) -> tuple[dict, dict]:
    """(results by scene set and controller, the shards' common meta) of shard payloads; ValueError on
    shards that do not make up one run exactly."""
    names = names or [str(i) for i in range(len(payloads))]
    if not payloads:
        raise ValueError("no shards given")
    first = payloads[0]["meta"]
    for name, payload in zip(names, payloads, strict=True):
        meta = payload["meta"]
        for key in SETTINGS:
            if meta.get(key) != first.get(key):
                raise ValueError(
                    f"shard {name} was run with {key} = {meta.get(key)!r}, shard {names[0]} with "
                    f"{first.get(key)!r}: shards of different settings cannot be merged"
                )
        sets = {s: sorted(v) for s, v in payload["by_scenes"].items()}
        want = {s: sorted(v) for s, v in payloads[0]["by_scenes"].items()}
        if sets != want:
            raise ValueError(
                f"shard {name} ran controllers {sets}, shard {names[0]} {want}: shards of different "
                "controllers cannot be merged"
            )
    shards = [tuple(int(x) for x in p["meta"]["shard"].split("/")) for p in payloads]
    counts = {n for _, n in shards}
    if len(counts) != 1:
        raise ValueError(f"shards of different shard counts cannot be merged: {sorted(counts)}")
    (n,) = counts
    seen: dict[int, str] = {}
    for name, (i, _) in zip(names, shards, strict=True):
        if i in seen:
            raise ValueError(f"shard {i}/{n} given twice ({seen[i]} and {name})")
        seen[i] = name
    missing = sorted(set(range(n)) - set(seen))
    if missing:
        raise ValueError(f"shards {[f'{i}/{n}' for i in missing]} are missing (have {sorted(seen)})")
    results = {
        label: {
            ctrl: _merge_entries([p["by_scenes"][label][ctrl] for p in payloads], f"{label}/{ctrl}")
            for ctrl in ctrls
        }
        for label, ctrls in payloads[0]["by_scenes"].items()
    }
    return results, first


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="lerobot-formation-bench-merge", description=__doc__.split("\n")[0])
    ap.add_argument("shards", nargs="+", help="the output folders of the shards (each with results.json)")
    ap.add_argument("--out", required=True, help="folder of the merged results.json and tables.md")
    ap.add_argument("--overwrite", action="store_true", help="replace a run --out already holds")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        payloads = [read_shard(Path(f)) for f in args.shards]
        results, meta = merge_shards(payloads, args.shards)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        print(f"error: --out {out} is a file, not a folder", file=sys.stderr)
        return 2
    held = existing_run(out)
    if held and not args.overwrite:
        print(
            f"error: --out {out} already holds a run ({held}); add --overwrite to replace it, or choose "
            "another folder",
            file=sys.stderr,
        )
        return 2
    out.mkdir(parents=True, exist_ok=True)
    run = BenchSettings(
        scenes=meta["scenes"],
        unseen=meta.get("unseen"),
        seed=meta.get("seed"),
        options=ControllerOptions(
            policy_path=meta.get("policy_path"),
            candidates=meta.get("candidates"),
            num_inference_steps=meta.get("num_inference_steps"),
        ),
        order=controller_names(),
        policy_controllers=tuple(n for n in controller_names() if needs_policy(n)),
    )
    report = SamplingReport()
    sampling = meta.get("scene_sampling") or {}
    report.drawn, report.accepted = sampling.get("drawn", 0), sampling.get("accepted", 0)
    report.rejected_start = sampling.get("rejected_start_covered", 0)
    report.rejected_goal = sampling.get("rejected_obstacle_near_goal", 0)
    report.rejected_passage = sampling.get("rejected_no_passage", 0)
    # checked, as the shards ran
    conditions = Conditions(**(meta.get("conditions") or {})).changed()
    unseen_conditions = Conditions(**(meta.get("unseen_conditions") or {})).changed()
    label = next(iter(results))
    write_results(
        out, results, label, run, report, conditions=conditions, unseen_conditions=unseen_conditions
    )
    for set_label, entries in results.items():
        for ctrl, entry in entries.items():
            lo, hi = entry["success_ci95"]
            print(
                f"[{set_label}] {ctrl}: success {entry['success_rate']:.1%} [{lo:.0%}, {hi:.0%}] of "
                f"{entry['n_episodes']} ({collisions_text(entry)}, timeouts {entry['timeouts']})"
            )
    print(f"merged {len(payloads)} shards into {out / 'results.json'}, {out / 'tables.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
