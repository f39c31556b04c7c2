"""Print the level table (the table of docs/log.md's level-table entries) from bench output folders.

    python scripts/level_table.py outputs/levels/level0 outputs/levels/level1 ... \
        [--name diffusion="default, standard"]

Each folder is one ``lerobot-formation-bench --out`` run on one scene set (``levelK:N``); several
folders of the same set (say, a rerun of one controller) are merged, the later folder winning for a
controller both hold. ``FOLDER@TAG`` keys that folder's controllers ``KEY@TAG``, so another model's
rows stand beside the default's (label them with ``--name KEY@TAG=LABEL``). One row per level and controller: success % with its Wilson 95 % interval,
collisions (with "(k struck)": k of them a moving obstacle struck a team that was not closing on
it, ``core.episodes.metrics.mover_strikes``) / timeouts, the means of control smoothness and jerk (successful episodes), the mean of
the episodes' minimum clearance and, for controllers with a safety layer, the filter's
interventions per 100 steps and the share of replans where no candidate was safe (and, with
a route hint, the share where route pursuit's proposal was kept). ``--compact``
prints the README's form instead: one row per level, one column per controller (success % [Wilson],
collisions (struck)/timeouts (scenes)).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

ORDER = [
    "pac",
    "mppi",
    "route-pursuit",
    "route-pursuit-safe",
    "route-pursuit-guided",
    "diffusion",
    "diffusion-guided",
    "diffusion-safe",
    "pac-privileged",
]
NAMES = {
    "pac": "PAC",
    "mppi": "MPPI",
    "route-pursuit": "route pursuit",
    "route-pursuit-safe": "route pursuit + the default's safety layer",
    "route-pursuit-guided": "route pursuit, guided",
    "diffusion": "default, standard",
    "diffusion-guided": "default, one guided sample",
    "diffusion-safe": "default, best-of-10 + CBF",
    "pac-privileged": "privileged expert (reference: sees the true world)",
}


def _collisions(m: dict) -> str:
    """Collisions, with how many of them a moving obstacle struck a team not closing on it
    (``core.episodes.metrics.mover_strikes``) where a run counted them and any happened."""
    struck = m.get("struck_by_mover")
    return f"{m['collisions']} ({struck} struck)" if struck else f"{m['collisions']}"


def _row(level: str, key: str, name: str, m: dict) -> str:
    lo, hi = m["success_ci95"]
    safety = m.get("safety") or {}
    if "safe" in key and safety.get("steps"):  # standard sampling counts zeros
        interventions = (
            f"{100 * safety['filter_intervention_rate']:.2f} / {100 * safety['replans_none_safe_rate']:.1f}"
        )
        if safety.get("proposals"):  # a layer with route pursuit's proposal: how often it was kept
            interventions += f" / {100 * safety['proposal_rate']:.1f}"
    else:
        interventions = "-"
    return (
        f"| {level} ({m['n_episodes']}) | {name} | {100 * m['success_rate']:.1f} "
        f"[{100 * lo:.0f}, {100 * hi:.0f}] | {_collisions(m)} / {m['timeouts']} | "
        f"{m['control_smoothness']['mean']:.3f} | {m['jerk']['mean']:.3f} | "
        f"{m['min_clearance']['mean']:.3f} | {interventions} |"
    )


def _ordered(keys) -> list[str]:
    def rank(key: str):
        base, _, tag = key.partition("@")
        return (tag, ORDER.index(base) if base in ORDER else len(ORDER), base)

    return sorted(keys, key=rank)


def _compact(levels: dict[str, dict], names: dict[str, str]) -> None:
    keys = _ordered({k for metrics in levels.values() for k in metrics})
    print("| level | " + " | ".join(names.get(k, k) for k in keys) + " |")
    print("|---" * (len(keys) + 1) + "|")
    for level in sorted(levels):
        metrics = levels[level]
        cells = []
        for k in keys:
            m = metrics.get(k)
            if m is None:
                cells.append("-")
                continue
            lo, hi = m["success_ci95"]
            cells.append(
                f"{100 * m['success_rate']:.1f} [{100 * lo:.0f}, {100 * hi:.0f}], "
                f"{_collisions(m)}/{m['timeouts']} ({m['n_episodes']})"
            )
        print(f"| {level} | " + " | ".join(cells) + " |")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+", metavar="FOLDER[@TAG]")
    ap.add_argument(
        "--name", action="append", default=[], metavar="KEY=LABEL", help="a controller's row label"
    )
    ap.add_argument("--compact", action="store_true", help="one row per level (the README's table)")
    args = ap.parse_args(argv)
    names = dict(NAMES)
    for item in args.name:
        key, sep, label = item.partition("=")
        if not sep:
            ap.error(f"--name takes KEY=LABEL, got {item!r}")
        names[key] = label
    levels: dict[str, dict] = {}
    for spec in args.folders:
        folder, _, tag = spec.partition("@")
        folder = Path(folder)
        path = folder / "results.json"
        if not path.is_file():
            ap.error(f"{folder} holds no results.json")
        results = json.loads(path.read_text())
        level = results["meta"]["scenes"].split(":")[0]
        levels.setdefault(level, {}).update(
            {
                f"{k}@{tag}" if tag else k: v
                for k, v in results.items()
                if isinstance(v, dict) and "success_rate" in v
            }
        )
    if args.compact:
        _compact(levels, names)
        return
    print(
        "| level (scenes) | controller | success % [Wilson 95 %] | collisions / timeouts | "
        "smoothness | jerk | min clearance [m] | filter interventions / 100 steps, no safe candidate %, "
        "route proposal kept % |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for level in sorted(levels):
        metrics = levels[level]
        for key in _ordered(metrics):
            print(_row(level, key, names.get(key, key), metrics[key]))


if __name__ == "__main__":
    main()
