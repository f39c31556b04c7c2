"""The bench's figures: per controller, the controllers side by side, and the success chart.

``draw_bench_figures`` draws them all after ``results.json`` and ``tables.md`` are written; a figure
that fails is reported as one line and skipped, never losing the results.
"""

from __future__ import annotations

import sys
from pathlib import Path

from lerobot_formation.core.episodes.rollout import EpisodeRecords
from lerobot_formation.core.world.sampling import UNSEEN_SEED_START
from lerobot_formation.core.world.scenes import Scenes


def write_figures(
    out: Path, name: str, rec: EpisodeRecords, scenes: Scenes, title: str = "", spec: str = ""
) -> list[str]:
    """The per-controller figures, files named ``name``_*.png, titled ``title`` (default ``name``);
    ``spec`` (the --scenes value) names each scene's preset in the panel titles."""
    from lerobot_formation.bench.plots import (
        plot_failures,
        plot_final_error_histogram,
        plot_formation_errors,
        plot_trajectories,
    )
    from lerobot_formation.bench.scene_sets import scene_set_presets

    title = title or name
    presets = scene_set_presets(spec, len(scenes)) if spec else None
    shown = list(range(min(6, len(rec))))  # the same first scenes for every controller
    files = [
        plot_trajectories(rec, scenes, shown, out / f"{name}_trajectories.png", title=title, presets=presets),
        plot_formation_errors(
            rec, shown, out / f"{name}_formation_error.png", title=title, scenes=scenes, presets=presets
        ),
        plot_final_error_histogram(rec, out / f"{name}_final_error_hist.png", title=title),
    ]
    if (rec.outcome != 1).any():
        files.append(plot_failures(rec, scenes, out / f"{name}_failures.png", title=title, presets=presets))
    return [f.name for f in files]


def write_comparison_figure(
    out: Path,
    label: str,
    records: dict[str, EpisodeRecords],
    scenes: Scenes,
    spec: str = "",
    seed: int = UNSEEN_SEED_START,
) -> str:
    from lerobot_formation.bench.plots import comparison_scenes, plot_controller_comparison, scene_set_label
    from lerobot_formation.bench.scene_sets import scene_set_presets

    path = out / f"controllers_{label}.png"
    title = scene_set_label(spec, seed) if spec else label
    presets = scene_set_presets(spec, len(scenes)) if spec else None
    shown = comparison_scenes(records, 3)
    return plot_controller_comparison(records, scenes, shown, path, title=title, presets=presets).name


def write_success_figure(out: Path, results: dict[str, dict], specs: dict[str, str], seed: int) -> str:
    from lerobot_formation.bench.plots import plot_success_rates, scene_set_label

    # Each set named by what it is (the demo's two sets are both unseen; the second is the hard suite).
    counts = {}
    for s, res in results.items():
        name = scene_set_label(specs[s], seed)
        name = f"{name} ({specs[s]})" if name in counts else name  # e.g. random:50 and random:20
        counts[name] = {
            c: (round(r["success_rate"] * r["n_episodes"]), r["n_episodes"]) for c, r in res.items()
        }
    return plot_success_rates(counts, out / "success_rates.png").name


def draw_bench_figures(
    out: Path,
    results: dict[str, dict],
    records: dict[str, dict[str, EpisodeRecords]],
    scenes: dict[str, Scenes],
    specs: dict[str, str],
    seed: int,
) -> tuple[list[str], list[str]]:
    """Every figure of a bench run: per controller and scene set, the controllers side by side (for a
    set of several), the success chart. Each entry of ``results[set][controller]["figures"]`` gets
    its files. A figure that raises is reported as one ``warning:`` line on stderr and skipped.
    Returns (the files drawn, those lines without the prefix)."""
    from lerobot_formation.bench.plots import scene_set_label  # matplotlib only when drawing

    failed: list[str] = []

    def attempt(what: str, draw, *args):
        try:
            return draw(*args)
        except Exception as e:  # noqa: BLE001  (a figure never costs the results; say which failed)
            failed.append(f"figure {what} not drawn: {type(e).__name__}: {e}")
            print(f"warning: {failed[-1]}", file=sys.stderr)
            return None

    for label, set_records in records.items():
        spec = specs.get(label, "")
        for name, rec in set_records.items():
            title = f"{name} on {scene_set_label(spec, seed)}" if spec else ""
            stem = f"{name}_{label}"
            files = attempt(f"{stem}_*.png", write_figures, out, stem, rec, scenes[label], title, spec)
            results[label][name]["figures"] = files or []
        if len(set_records) > 1:
            shared = attempt(
                f"controllers_{label}.png",
                write_comparison_figure,
                out,
                label,
                set_records,
                scenes[label],
                spec,
                seed,
            )
            if shared:
                for name in set_records:
                    results[label][name]["figures"].append(shared)
    success = attempt("success_rates.png", write_success_figure, out, results, specs, seed)
    drawn = sorted({f for res in results.values() for r in res.values() for f in r["figures"]})
    return drawn + ([success] if success else []), failed
