"""The bench's figures: per controller, the controllers side by side, and the success chart."""

from __future__ import annotations

from pathlib import Path

from lerobot_formation.core.rollout import EpisodeRecords
from lerobot_formation.core.scene import Scenes
from lerobot_formation.paper_tables import SET_TITLES, is_paper_protocol


def write_figures(out: Path, name: str, rec: EpisodeRecords, scenes: Scenes) -> list[str]:
    from lerobot_formation.plots import (
        plot_failures,
        plot_final_error_histogram,
        plot_formation_errors,
        plot_trajectories,
    )

    shown = list(range(min(6, len(rec))))  # the same first scenes for every controller
    files = [
        plot_trajectories(rec, scenes, shown, out / f"{name}_trajectories.png", title=name),
        plot_formation_errors(rec, shown, out / f"{name}_formation_error.png", title=name, scenes=scenes),
        plot_final_error_histogram(rec, out / f"{name}_final_error_hist.png", title=name),
    ]
    if (rec.outcome != 1).any():
        files.append(plot_failures(rec, scenes, out / f"{name}_failures.png", title=name))
    return [f.name for f in files]


def write_comparison_figure(
    out: Path, label: str, records: dict[str, EpisodeRecords], scenes: Scenes, spec: str = ""
) -> str:
    from lerobot_formation.plots import comparison_scenes, plot_controller_comparison

    path = out / f"controllers_{label}.png"
    title = SET_TITLES.get(label, label) if is_paper_protocol(spec) else f"{spec} scenes (unseen)"
    return plot_controller_comparison(records, scenes, comparison_scenes(records, 3), path, title=title).name


def write_success_figure(out: Path, results: dict[str, dict]) -> str:
    from lerobot_formation.plots import plot_success_rates

    counts = {
        f"{s} scenes": {
            c: (round(r["success_rate"] * r["n_episodes"]), r["n_episodes"]) for c, r in res.items()
        }
        for s, res in results.items()
    }
    return plot_success_rates(counts, out / "success_rates.png").name
