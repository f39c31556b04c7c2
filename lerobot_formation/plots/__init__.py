"""Figures in the spirit of the paper's Fig. 3 and 4 (matplotlib, imported only when plotting)."""

from lerobot_formation.plots.figures import (
    plot_failures,
    plot_final_error_histogram,
    plot_formation_errors,
    plot_trajectories,
)

__all__ = ["plot_failures", "plot_final_error_histogram", "plot_formation_errors", "plot_trajectories"]
