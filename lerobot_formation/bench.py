"""``lerobot-formation-bench``: run controllers on a scene set and write results and figures.

Example::

    lerobot-formation-bench --controllers pac --scenes random:50 --seed 1000000 --out outputs/bench

Scenes: ``random:N`` (the valid scenes of seeds S..S+N-1, S = --seed, default 1_000_000, disjoint
from the dataset's seeds), or a scenes JSON file. Writes ``OUT/results.json`` (keyed by controller:
success_rate, n_episodes, collisions, timeouts, episodes, ...) and PNG figures.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from lerobot_formation.core.dynamics import FormationParams
from lerobot_formation.core.rollout import PACController
from lerobot_formation.core.scene import UNSEEN_SEED_START, Scenes, load_scenes, sample_scenes
from lerobot_formation.evaluation import basic_summary, evaluate

CONTROLLERS = ("pac",)


def parse_scenes(spec: str, seed: int) -> Scenes:
    """``random:N`` or a path to a scenes JSON file."""
    if spec.startswith("random:"):
        try:
            n = int(spec.split(":", 1)[1])
        except ValueError as e:
            raise ValueError(f"--scenes random:N needs an integer N, got {spec!r}") from e
        if n < 1:
            raise ValueError(f"--scenes random:N needs N >= 1, got {n}")
        return sample_scenes(seed + np.arange(n))
    return load_scenes(spec)


def make_controller(name: str, params: FormationParams):
    if name == "pac":
        return PACController(params=params)
    raise ValueError(f"unknown controller {name!r}; choose from {CONTROLLERS}")


def write_figures(out: Path, name: str, rec, scenes: Scenes) -> list[str]:
    from lerobot_formation.plots import plot_formation_errors, plot_trajectories

    ok = np.flatnonzero(rec.outcome == 1)
    shown = list(ok[:2]) if len(ok) else list(range(min(2, len(rec))))
    files = [
        plot_trajectories(rec, scenes, shown, out / f"{name}_trajectories.png", title=name),
        plot_formation_errors(rec, shown, out / f"{name}_formation_error.png", title=name),
    ]
    return [f.name for f in files]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="lerobot-formation-bench", description=__doc__.split("\n")[0])
    ap.add_argument("--controllers", default="pac", help=f"comma-separated, from {CONTROLLERS}")
    ap.add_argument("--scenes", default="random:20", help="random:N or FILE.json")
    ap.add_argument("--seed", type=int, default=UNSEEN_SEED_START, help="first seed for random:N")
    ap.add_argument("--out", default="outputs/bench", help="output folder")
    ap.add_argument("--no-figures", action="store_true")
    args = ap.parse_args(argv)
    names = [c.strip() for c in args.controllers.split(",") if c.strip()]
    for n in names:
        if n not in CONTROLLERS:
            ap.error(f"unknown controller {n!r}; choose from {CONTROLLERS}")
    try:
        scenes = parse_scenes(args.scenes, args.seed)
    except ValueError as e:
        ap.error(str(e))
    params = FormationParams()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for name in names:
        t0 = time.perf_counter()
        rec = evaluate(make_controller(name, params), scenes, params, progress=True, desc=name)
        entry = basic_summary(rec, scenes)
        entry["wall_time_s"] = time.perf_counter() - t0
        if not args.no_figures:
            entry["figures"] = write_figures(out, name, rec, scenes)
        results[name] = entry
        print(
            f"{name}: success {entry['success_rate']:.1%} of {entry['n_episodes']} "
            f"(collisions {entry['collisions']}, timeouts {entry['timeouts']}) in {entry['wall_time_s']:.1f} s"
        )
    tmp = out / "results.json.tmp"
    tmp.write_text(json.dumps(results, indent=1))
    os.replace(tmp, out / "results.json")
    print(f"wrote {out / 'results.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
