"""Matplotlib figures of batched rollouts (EpisodeRecords + Scenes)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from lerobot_formation.core.formation_graph import FormationGraph  # noqa: E402
from lerobot_formation.core.rollout import OUTCOME_NAMES, EpisodeRecords  # noqa: E402
from lerobot_formation.core.scene import Scenes  # noqa: E402

AGENT_STYLE = [("L1", "tab:blue"), ("L2", "tab:cyan"), ("F1", "tab:orange"), ("F2", "tab:red")]


def _draw_episode(ax, rec: EpisodeRecords, scenes: Scenes, b: int, graph: FormationGraph, snapshots: int = 6):
    for (x, y, r), m in zip(scenes.obstacles[b], scenes.mask[b], strict=True):
        if m:
            ax.add_patch(plt.Circle((x, y), r, color="0.55", zorder=1))
    ax.add_patch(plt.Circle(tuple(scenes.goal[b]), 0.3, color="tab:green", alpha=0.3, zorder=1))
    ax.plot(*scenes.goal[b], "*", color="tab:green", ms=12, zorder=3)
    ep = rec.episode(b)
    pos = ep["positions"]
    for a in range(pos.shape[1]):
        name, color = AGENT_STYLE[a % len(AGENT_STYLE)]
        ax.plot(pos[:, a, 0], pos[:, a, 1], color=color, lw=1.2, label=name if a < 4 else None, zorder=2)
    for t in np.linspace(0, len(pos) - 1, snapshots).astype(int):
        for i, j in zip(graph.edge_i, graph.edge_j, strict=True):
            ax.plot(pos[t, [i, j], 0], pos[t, [i, j], 1], color="k", lw=0.6, alpha=0.6, zorder=2)
        ax.scatter(pos[t, :, 0], pos[t, :, 1], s=8, color="k", zorder=3)
    ax.set_aspect("equal")
    ax.set_xlim(-2, 8)
    ax.set_ylim(-2, 8)
    seed = int(scenes.seeds[b])
    ax.set_title(
        f"seed {seed}: {OUTCOME_NAMES[int(rec.outcome[b])]}, {int(rec.steps[b]) * rec.dt:.1f} s", fontsize=9
    )


def plot_trajectories(
    rec: EpisodeRecords, scenes: Scenes, indices, path: str | Path, title: str = "", graph=None
) -> Path:
    """Trajectories of all agents with formation snapshots, one panel per episode."""
    graph = graph or FormationGraph()
    indices = list(indices)
    fig, axs = plt.subplots(1, max(len(indices), 1), figsize=(4.2 * max(len(indices), 1), 4.2), squeeze=False)
    for ax, b in zip(axs[0], indices, strict=False):
        _draw_episode(ax, rec, scenes, b, graph)
    axs[0][0].legend(fontsize=7, loc="lower right")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_formation_errors(rec: EpisodeRecords, indices, path: str | Path, title: str = "") -> Path:
    """Formation error e_d and followers' velocity error over time for the given episodes."""
    fig, axs = plt.subplots(1, 2, figsize=(10, 3.6))
    for b in indices:
        ep = rec.episode(b)
        t = np.arange(len(ep["formation_error"])) * rec.dt
        axs[0].plot(t, ep["formation_error"], lw=1, label=f"episode {b}")
        axs[1].plot(t[1:], ep["follower_velocity_error"], lw=1, label=f"episode {b}")
    axs[0].set(xlabel="time [s]", ylabel="formation error $e_d$ [m]", yscale="log")
    axs[1].set(xlabel="time [s]", ylabel="follower velocity error [m/s]", yscale="log")
    for ax in axs:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_final_error_histogram(rec: EpisodeRecords, path: str | Path, n: int = 50, title: str = "") -> Path:
    """Histogram of the final formation and follower-velocity errors over up to n successful runs."""
    ok = np.flatnonzero(rec.outcome == 1)[:n]
    fe = [rec.episode(b)["formation_error"][-1] for b in ok]
    ve = [rec.episode(b)["follower_velocity_error"][-1] for b in ok if rec.steps[b] > 0]
    fig, axs = plt.subplots(1, 2, figsize=(9, 3.4))
    axs[0].hist(fe, bins=20, color="tab:blue")
    axs[0].set(xlabel="final formation error [m]", ylabel="episodes")
    axs[1].hist(ve, bins=20, color="tab:orange")
    axs[1].set(xlabel="final follower velocity error [m/s]")
    fig.suptitle(f"{title} ({len(ok)} successful runs)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_failures(rec: EpisodeRecords, scenes: Scenes, path: str | Path, title: str = "", graph=None) -> Path:
    """A 3x3 grid of failure cases (collisions and timeouts)."""
    graph = graph or FormationGraph()
    bad = np.flatnonzero(rec.outcome != 1)[:9]
    fig, axs = plt.subplots(3, 3, figsize=(10, 10), squeeze=False)
    for k, ax in enumerate(axs.ravel()):
        if k < len(bad):
            _draw_episode(ax, rec, scenes, bad[k], graph, snapshots=3)
        else:
            ax.axis("off")
    fig.suptitle(f"{title}: {len(bad)} failure cases shown")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return Path(path)
