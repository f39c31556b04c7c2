"""Figures in the spirit of the paper's Fig. 3 and 4 (matplotlib, imported only when plotting)."""

from lerobot_formation.bench.plots.figures import (
    collision_point,
    comparison_scenes,
    plot_controller_comparison,
    plot_failures,
    plot_final_error_histogram,
    plot_formation_errors,
    plot_success_rates,
    plot_trajectories,
    scene_label,
    scene_set_label,
)

__all__ = [
    "collision_point",
    "comparison_scenes",
    "plot_controller_comparison",
    "plot_failures",
    "plot_final_error_histogram",
    "plot_formation_errors",
    "plot_success_rates",
    "plot_trajectories",
    "scene_label",
    "scene_set_label",
]
