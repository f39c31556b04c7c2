"""Fast batched closed-loop evaluation: every episode of a scene set runs at once on the core.

``evaluate(controller, scenes)`` steps all live episodes with one ``dynamics.step`` call and one
controller call per control step, then computes the per-episode records. It is the engine behind
``lerobot-formation-bench`` and the dataset generator; ``run_set`` is the bench's evaluation run (the
named controllers on one scene set, with their metrics and figures).
"""

from __future__ import annotations

import sys
import time

from lerobot_formation.bench_results import controller_results, safety_rates
from lerobot_formation.controllers import make_controller
from lerobot_formation.core.conditions import Conditions
from lerobot_formation.core.dynamics import FormationParams
from lerobot_formation.core.rollout import Controller, EpisodeRecords, rollout
from lerobot_formation.core.scene import Scenes


def evaluate(
    controller: Controller,
    scenes: Scenes,
    params: FormationParams | None = None,
    progress: bool = False,
    desc: str | None = None,
    conditions: Conditions | None = None,
) -> EpisodeRecords:
    """Roll ``controller`` out on every scene (batched) under ``conditions`` (None: none) and return
    the records."""
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(scenes), desc=desc or getattr(controller, "name", "eval"), unit="ep")
    try:
        return rollout(
            scenes,
            controller,
            params,
            progress=bar.update if bar is not None else None,
            conditions=conditions,
        )
    finally:
        if bar is not None:
            bar.close()


class BenchInputError(ValueError):
    """A bad input found while running (a controller that this checkpoint cannot serve, ...): reported
    as one ``error:`` line, exit code 2, after writing the results of the controllers that finished."""


def run_set(
    names,
    scenes,
    params,
    args,
    label: str,
    bundle,
    into: dict | None = None,
    records: dict | None = None,
    conditions: Conditions | None = None,
    indices=None,
) -> dict:
    """Run the controllers ``names`` on ``scenes`` under ``conditions``; each finished controller's
    entry is put into ``into`` (default: a new dict, returned) at once, so a later failure keeps it.
    ``records``: a dict that also receives each controller's ``EpisodeRecords`` (for the figures, drawn
    after the results are written: ``bench_figures.draw_bench_figures``). ``indices``: each scene's
    index in its whole scene set (a shard's), default 0..len-1."""
    results = into if into is not None else {}
    spec = (args.unseen if label == "unseen" else args.scenes) or ""
    for name in names:
        t0 = time.perf_counter()
        try:
            ctrl = make_controller(name, params, args, bundle)
        except ValueError as e:
            raise BenchInputError(f"controller {name}: {e}") from e
        # Progress bars only on a terminal (tqdm writes to stderr), so logs stay free of them.
        progress = not args.no_progress and sys.stderr.isatty()
        rec = evaluate(
            ctrl, scenes, params, progress=progress, desc=f"{name} ({label})", conditions=conditions
        )
        entry = controller_results(rec, scenes, indices)
        entry["wall_time_s"] = time.perf_counter() - t0
        if getattr(ctrl, "stats", None):  # the safety layer's interventions
            entry["safety"] = {**ctrl.stats, **safety_rates(ctrl.stats)}
        entry["scenes"] = label
        entry["figures"] = []
        if records is not None:
            records[name] = rec
        results[name] = entry
        lo, hi = entry["success_ci95"]
        print(  # the set by its spec (random:50, hard:20, dataset:100): "unseen" is not what it is
            f"[{spec or label}] {name}: success {entry['success_rate']:.1%} [{lo:.0%}, {hi:.0%}] of {entry['n_episodes']} "
            f"(collisions {entry['collisions']}, timeouts {entry['timeouts']}) in {entry['wall_time_s']:.1f} s",
            flush=True,
        )
    return results
