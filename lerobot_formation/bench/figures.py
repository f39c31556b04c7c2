"""The bench's figures: per controller, the controllers side by side, and the success chart."""

from __future__ import annotations

from pathlib import Path

from lerobot_formation.core.rollout import EpisodeRecords
from lerobot_formation.core.scene import UNSEEN_SEED_START, Scenes


def write_figures(out: Path, name: str, rec: EpisodeRecords, scenes: Scenes, title: str = "") -> list[str]:
    """The per-controller figures, files named ``name``_*.png, titled ``title`` (default ``name``)."""
    from lerobot_formation.bench.plots import (
        plot_failures,
        plot_final_error_histogram,
        plot_formation_errors,
        plot_trajectories,
    )

    title = title or name
    shown = list(range(min(6, len(rec))))  # the same first scenes for every controller
    files = [
        plot_trajectories(rec, scenes, shown, out / f"{name}_trajectories.png", title=title),
        plot_formation_errors(rec, shown, out / f"{name}_formation_error.png", title=title, scenes=scenes),
        plot_final_error_histogram(rec, out / f"{name}_final_error_hist.png", title=title),
    ]
    if (rec.outcome != 1).any():
        files.append(plot_failures(rec, scenes, out / f"{name}_failures.png", title=title))
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

    path = out / f"controllers_{label}.png"
    title = scene_set_label(spec, seed) if spec else label
    return plot_controller_comparison(records, scenes, comparison_scenes(records, 3), path, title=title).name


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
