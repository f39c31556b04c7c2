"""Matplotlib figures of batched rollouts (EpisodeRecords + Scenes), in the spirit of the paper's Fig. 3-4.

Every panel has labelled axes with units. A scene is named by its preset (when the caller knows it),
its index in the scene set and its seed (when it has one), see ``scene_label``; every metric is
defined where it is drawn.
"""

from __future__ import annotations

import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from lerobot_formation.core.episodes.metrics import wilson_interval  # noqa: E402
from lerobot_formation.core.episodes.rollout import COLLISION, OUTCOME_NAMES, SUCCESS, TIMEOUT, EpisodeRecords  # noqa: E402
from lerobot_formation.core.world.dynamics import FormationParams  # noqa: E402
from lerobot_formation.core.world.formation_graph import FormationGraph  # noqa: E402
from lerobot_formation.core.world.geometry import agent_clearances  # noqa: E402
from lerobot_formation.core.world.sampling import UNSEEN_SEED_START
from lerobot_formation.core.world.scenes import Scenes  # noqa: E402

AGENT_COLORS = ("tab:blue", "tab:cyan", "tab:orange", "tab:purple")
OUTCOME_COLORS = {"success": "tab:green", "collision": "tab:red", "timeout": "tab:orange"}
MAX_TRAJECTORY_PANELS = 6
MAX_FAILURE_PANELS = 9


def scene_label(scenes: Scenes, b: int, presets: Sequence[str] | None = None) -> str:
    """The scene's preset (when known), its index in the scene set and its seed (when it has one):
    ``"gates scene 3, seed 1000000"``, ``"scene 12"`` (a scenes file). The index tells apart scenes
    that share a seed (the hard suite draws the same seeds from each of its presets)."""
    head = f"{presets[b]} scene {b}" if presets is not None else f"scene {b}"
    seed = int(scenes.seeds[b])
    return f"{head}, seed {seed}" if seed >= 0 else head


def _grid(n: int, max_cols: int = 3) -> tuple[int, int]:
    cols = max(1, min(max_cols, n))
    return int(np.ceil(max(n, 1) / cols)), cols


def _suptitle(fig, text: str, fontsize: float = 12) -> None:
    """The figure title, broken into lines that fit the figure's width (a long scene-set name)."""
    per_line = int(fig.get_size_inches()[0] * 72 / (0.55 * fontsize))  # ~0.55 em per character
    fig.suptitle(textwrap.fill(text, per_line), fontsize=fontsize)


def _save(fig, path: str | Path, dpi: int = 110) -> Path:
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return Path(path)


def collision_point(
    rec: EpisodeRecords, scenes: Scenes, b: int, agent_radius: float = 0.1
) -> tuple[int, np.ndarray] | None:
    """(agent index, contact point (2,) [m]) of a collided episode, None for any other outcome.

    The agent is the one whose clearance is negative at the last step (the most negative if several
    overlap an obstacle); the point is on that obstacle's surface, towards the agent's centre.
    """
    if int(rec.outcome[b]) != COLLISION:
        return None
    pos = rec.positions[b, int(rec.steps[b])]  # (N, 2)
    obstacles = scenes.obstacles[b].copy()
    if rec.obstacle_paths is not None:  # moving obstacles: where they were at the end
        now = rec.obstacle_paths[b, int(rec.steps[b])]
        ok = np.isfinite(now).all(axis=1)
        obstacles[ok, :2] = now[ok]
    clear = agent_clearances(pos[None], obstacles[None], agent_radius)[0]  # (N,)
    agent = int(np.argmin(clear))
    gaps = np.linalg.norm(pos[agent] - obstacles[:, :2], axis=-1) - obstacles[:, 2]
    gaps[~scenes.mask[b]] = np.inf
    x, y, r = obstacles[int(np.argmin(gaps))]
    away = pos[agent] - (x, y)
    norm = np.linalg.norm(away)
    point = np.array([x, y]) + (r * away / norm if norm > 0 else 0.0)
    return agent, point


def _limits(rec: EpisodeRecords, scenes: Scenes, indices: Sequence[int], margin: float = 0.6):
    """Square axis limits [m] that hold the trajectories, real obstacles, start and goal of ``indices``."""
    pts = [scenes.goal[list(indices)], scenes.start[list(indices), :2]]
    for b in indices:
        ob = scenes.obstacles[b][scenes.mask[b]]
        pts += [ob[:, :2] - ob[:, 2:], ob[:, :2] + ob[:, 2:]]
        pos = rec.positions[b, : int(rec.steps[b]) + 1].reshape(-1, 2)
        pts.append(pos[np.isfinite(pos).all(axis=1)])
        if rec.obstacle_paths is not None:  # moving obstacles' centres over the episode
            track = rec.obstacle_paths[b, : int(rec.steps[b]) + 1][:, scenes.mask[b]].reshape(-1, 2)
            pts.append(track[np.isfinite(track).all(axis=1)])
    pts = np.concatenate(pts)
    lo, hi = pts.min(axis=0) - margin, pts.max(axis=0) + margin
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2
    return (centre[0] - half, centre[0] + half), (centre[1] - half, centre[1] + half)


def _draw_episode(
    ax,
    rec: EpisodeRecords,
    scenes: Scenes,
    b: int,
    graph: FormationGraph,
    snapshots: int = 6,
    limits=None,
    params: FormationParams | None = None,
    title: str | None = None,
    presets: Sequence[str] | None = None,
) -> None:
    """Obstacles (``_draw_obstacles``), goal (disc: the goal tolerance), every agent's path, formation
    snapshots and, for a collision, the contact point and the agent that hit; for a timeout, the final
    midpoint."""
    params = params or FormationParams()
    agent_radius = params.agent_radius
    _draw_obstacles(ax, rec, scenes, b)
    ax.add_patch(
        plt.Circle(tuple(scenes.goal[b]), params.goal_tolerance, color="tab:green", alpha=0.25, zorder=1)
    )
    ax.plot(*scenes.goal[b], "*", color="tab:green", ms=11, zorder=3)
    pos = rec.episode(b)["positions"]  # (T_b + 1, N, 2)
    for a in range(pos.shape[1]):
        ax.plot(pos[:, a, 0], pos[:, a, 1], color=AGENT_COLORS[a % len(AGENT_COLORS)], lw=1.2, zorder=2)
    for t in np.unique(np.linspace(0, len(pos) - 1, snapshots).astype(int)):
        for i, j in zip(graph.edge_i, graph.edge_j, strict=True):
            ax.plot(pos[t, [i, j], 0], pos[t, [i, j], 1], color="k", lw=0.6, alpha=0.6, zorder=2)
        ax.scatter(pos[t, :, 0], pos[t, :, 1], s=7, color="k", zorder=3)
    outcome = OUTCOME_NAMES[int(rec.outcome[b])]
    detail = outcome
    hit = collision_point(rec, scenes, b, agent_radius)
    if hit is not None:
        agent, point = hit
        name = graph.agents[agent]
        ax.add_patch(
            plt.Circle(tuple(pos[-1, agent]), agent_radius, fill=False, ec="tab:red", lw=1.5, zorder=4)
        )
        ax.plot(*point, "X", color="tab:red", mec="k", mew=0.8, ms=11, zorder=5)
        ax.annotate(
            name, point, xytext=(6, 6), textcoords="offset points", color="tab:red", weight="bold", zorder=5
        )
        detail = f"collision ({name})"
    elif outcome == "timeout":
        ax.plot(*rec.poses[b, int(rec.steps[b]), :2], "s", color="tab:orange", mec="k", ms=7, zorder=5)
    ax.set_aspect("equal")
    xlim, ylim = limits or _limits(rec, scenes, [b])
    ax.set(xlim=xlim, ylim=ylim, xlabel="x [m]", ylabel="y [m]")
    ax.tick_params(labelsize=7)
    head = title if title is not None else scene_label(scenes, b, presets)
    text = f"{head}: {detail}, {int(rec.steps[b]) * rec.dt:.1f} s"
    if len(text) > 48:  # about what fits over a PANEL-wide axis at 9 pt
        text = f"{head}\n{detail}, {int(rec.steps[b]) * rec.dt:.1f} s"
    ax.set_title(text, fontsize=9)


def _draw_obstacles(ax, rec: EpisodeRecords, scenes: Scenes, b: int) -> None:
    """Episode b's obstacles: filled grey discs where they stand at its end. Under realistic conditions
    (``EpisodeRecords.seen_step`` / ``obstacle_paths`` set), an obstacle the team never sensed is drawn
    faint with a dashed outline (the true map beyond the sensed one), and a moving obstacle's path is a
    dotted line from a dashed outline of where it started."""
    seen = rec.seen_step[b] if rec.seen_step is not None else None
    paths = rec.obstacle_paths[b, : int(rec.steps[b]) + 1] if rec.obstacle_paths is not None else None
    for m, ((x, y, r), present) in enumerate(zip(scenes.obstacles[b], scenes.mask[b], strict=True)):
        if not present:
            continue
        if paths is not None:
            track = paths[:, m][np.isfinite(paths[:, m]).all(axis=1)]
            if len(track) and np.ptp(track, axis=0).max() > 1e-9:  # it moved
                ax.plot(track[:, 0], track[:, 1], ":", color="tab:brown", lw=1.2, zorder=1)
                ax.add_patch(plt.Circle(tuple(track[0]), r, fill=False, ec="tab:brown", ls="--", lw=0.8))
            if len(track):
                x, y = track[-1]
        if seen is not None and seen[m] < 0:
            ax.add_patch(plt.Circle((x, y), r, color="0.6", alpha=0.2, zorder=1))
            ax.add_patch(plt.Circle((x, y), r, fill=False, ec="0.35", ls="--", lw=0.8, zorder=1))
        else:
            ax.add_patch(plt.Circle((x, y), r, color="0.6", zorder=1))


UNSENSED_MARK = Patch(
    facecolor=(0.6, 0.6, 0.6, 0.2), edgecolor="0.35", ls="--", label="obstacle never sensed"
)
MOVING_MARK = Line2D([], [], color="tab:brown", ls=":", label="moving obstacle: path from start (dashed)")


def _condition_marks(records: Sequence[EpisodeRecords], indices: Sequence[int]) -> list:
    """Legend entries for realistic conditions shown in the panels: never-sensed and moving obstacles."""
    marks = []
    if any(r.seen_step is not None and (r.seen_step[list(indices)] < 0).any() for r in records):
        marks.append(UNSENSED_MARK)
    if any(r.obstacle_paths is not None for r in records):
        marks.append(MOVING_MARK)
    return marks


PANEL = 3.7  # [in] side of one scene panel


def _panels(rows: int, cols: int):
    """A figure of rows x cols scene panels, at least 6.5 in wide so that titles and legend fit."""
    size = (max(PANEL * cols, 6.5), PANEL * rows + 0.9)
    return plt.subplots(rows, cols, figsize=size, squeeze=False)


def _finish_panels(
    fig,
    graph: FormationGraph,
    params: FormationParams,
    title: str,
    caption: str,
    records: Sequence[EpisodeRecords],
    indices: Sequence[int],
    outcomes: np.ndarray,
) -> None:
    """Title ``"{title}: {caption}"`` (``caption`` alone without a title) above the scene panels and one
    shared legend below them: agents, snapshots, obstacle, goal, the goal tolerance disc, then the
    markers of what the panels show: failures among ``outcomes`` (``_marks``) and the realistic
    conditions of ``records`` on scenes ``indices`` (``_condition_marks``)."""
    handles = [
        Line2D([], [], color=AGENT_COLORS[a % len(AGENT_COLORS)], label=name)
        for a, name in enumerate(graph.agents)
    ]
    handles += [
        Line2D([], [], color="k", lw=0.6, marker=".", label="formation snapshot"),
        Patch(color="0.6", label="obstacle"),
        Line2D([], [], color="tab:green", marker="*", ls="", ms=10, label="goal"),
        Patch(color="tab:green", alpha=0.25, label=f"goal tolerance ({params.goal_tolerance:g} m)"),
        *_marks(outcomes),
        *_condition_marks(records, indices),
    ]
    width, height = fig.get_size_inches()
    per_line = max(2, int(width / 1.3))
    lines = int(np.ceil(len(handles) / per_line))
    ncol = int(np.ceil(len(handles) / lines))
    fig.legend(handles=handles, loc="lower center", ncol=ncol, fontsize=8, frameon=False)
    _suptitle(fig, f"{title}: {caption}" if title else caption, fontsize=11)
    fig.tight_layout(rect=(0, 0.25 * lines / height, 1, 1))


def _plural(n: int, word: str) -> str:
    return f"{n} {word}" + ("" if n == 1 else "s")


COLLISION_MARK = Line2D([], [], color="tab:red", marker="X", mec="k", ls="", ms=9, label="collision point")
TIMEOUT_MARK = Line2D(
    [], [], color="tab:orange", marker="s", mec="k", ls="", ms=6, label="timeout: final midpoint"
)


def _marks(outcomes: np.ndarray) -> list:
    """Legend entries for the failure markers that appear in the panels."""
    return [m for m, o in ((COLLISION_MARK, COLLISION), (TIMEOUT_MARK, TIMEOUT)) if (outcomes == o).any()]


def plot_trajectories(
    rec: EpisodeRecords,
    scenes: Scenes,
    indices,
    path: str | Path,
    title: str = "",
    graph: FormationGraph | None = None,
    params: FormationParams | None = None,
    presets: Sequence[str] | None = None,
) -> Path:
    """Trajectories of all agents with formation snapshots: one panel per episode, up to 6, each titled
    with its scene (``scene_label``: preset, index in the set, seed)."""
    params = params or FormationParams()
    graph = graph or params.graph
    indices = list(indices)[:MAX_TRAJECTORY_PANELS]
    rows, cols = _grid(len(indices))
    fig, axs = _panels(rows, cols)
    for k, ax in enumerate(axs.ravel()):
        if k < len(indices):
            _draw_episode(ax, rec, scenes, indices[k], graph, params=params, presets=presets)
        else:
            ax.axis("off")
    caption = _plural(len(indices), "episode")
    _finish_panels(fig, graph, params, title, caption, [rec], indices, rec.outcome[indices])
    return _save(fig, path)


FOLLOWER_VELOCITY_ERROR_NOTE = (
    "formation error e_d = ||d - d*||: the distances d between the agents of the formation graph's edges "
    "against their template values d*. Follower velocity error: mean over the two followers of |v_i - v_i*|, v_i* the velocity of the "
    "follower's slot in the square the leaders carry (v + omega x r). A slot 1.1 m from the midpoint moves "
    "at up to 0.6 + 1.5 x 1.1 = 2.3 m/s when the team turns, and the error adds the follower's own "
    "velocity, so it can exceed the leaders' 0.6 m/s cap."
)


def plot_formation_errors(
    rec: EpisodeRecords,
    indices,
    path: str | Path,
    title: str = "",
    scenes: Scenes | None = None,
    presets: Sequence[str] | None = None,
) -> Path:
    """Formation error e_d and the followers' velocity error over time for the given episodes, with the
    velocity error defined under the panels (``FOLLOWER_VELOCITY_ERROR_NOTE``)."""
    fig, axs = plt.subplots(1, 2, figsize=(10, 4.4))
    for b in indices:
        ep = rec.episode(b)
        t = np.arange(len(ep["formation_error"])) * rec.dt
        label = scene_label(scenes, b, presets) if scenes is not None else f"episode {b}"
        axs[0].plot(t, ep["formation_error"], lw=1, label=label)
        axs[1].plot(t[1:], ep["follower_velocity_error"], lw=1, label=label)
    axs[0].set(
        xlabel="time [s]",
        ylabel="formation error $e_d$ [m]",
        yscale="log",
        title="formation error $e_d$ (see below)",
    )
    axs[1].set(
        xlabel="time [s]",
        ylabel="follower velocity error [m/s]",
        yscale="log",
        title="follower velocity error $|v_i - v_i^*|$ (see below)",
    )
    for ax in axs:
        ax.grid(alpha=0.3)
    # One legend beside both panels (the same episodes, the same colours), clear of the curves.
    fig.legend(*axs[0].get_legend_handles_labels(), loc="center right", fontsize=7, title="episode")
    fig.text(0.01, 0.01, textwrap.fill(FOLLOWER_VELOCITY_ERROR_NOTE, 150), fontsize=7, va="bottom")
    _suptitle(fig, title)
    fig.tight_layout(rect=(0, 0.13, 0.83, 1))
    return _save(fig, path)


def plot_final_error_histogram(
    rec: EpisodeRecords, path: str | Path, n: int | None = None, title: str = ""
) -> Path:
    """Histograms of the final formation and follower-velocity errors of the successful runs.

    Uses every successful run (the first ``n`` if given); the title gives the number actually used.
    """
    ok = np.flatnonzero(rec.outcome == SUCCESS)[:n]
    fe = np.array([rec.episode(b)["formation_error"][-1] for b in ok])
    ve = np.array([rec.episode(b)["follower_velocity_error"][-1] for b in ok if rec.steps[b] > 0])
    fig, axs = plt.subplots(1, 2, figsize=(9, 3.6))
    for ax, values, color, xlabel in (
        (axs[0], fe, "tab:blue", "final formation error $e_d$ [m]"),
        (axs[1], ve, "tab:orange", "final follower velocity error [m/s]"),
    ):
        if len(values):
            # White edges: two neighbouring bins of one height would otherwise read as one wide bin.
            ax.hist(values, bins=int(np.clip(len(values) // 3, 5, 20)), color=color, edgecolor="white")
        else:
            ax.text(0.5, 0.5, "no successful run", ha="center", va="center", transform=ax.transAxes)
        ax.set(xlabel=xlabel, ylabel="episodes")
        ax.xaxis.set_major_locator(MaxNLocator(5))
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(alpha=0.3)
    head = f"{title}: " if title else ""
    _suptitle(fig, f"{head}final errors of {len(ok)} successful runs (of {len(rec)} episodes)")
    fig.tight_layout()
    return _save(fig, path)


def plot_failures(
    rec: EpisodeRecords,
    scenes: Scenes,
    path: str | Path,
    title: str = "",
    graph: FormationGraph | None = None,
    params: FormationParams | None = None,
    presets: Sequence[str] | None = None,
) -> Path:
    """Failure cases (collisions, timeouts), up to 9, in a grid sized to their number.

    A collision is marked with a red X at the contact point, the colliding agent's disc circled and
    named; a timeout with an orange square at the final midpoint.
    """
    params = params or FormationParams()
    graph = graph or params.graph
    all_bad = np.flatnonzero(rec.outcome != SUCCESS)
    bad = all_bad[:MAX_FAILURE_PANELS]
    rows, cols = _grid(len(bad))
    fig, axs = _panels(rows, cols)
    for k, ax in enumerate(axs.ravel()):
        if k < len(bad):
            _draw_episode(ax, rec, scenes, bad[k], graph, snapshots=3, params=params, presets=presets)
        else:
            ax.axis("off")
    if not len(bad):
        axs[0][0].text(0.5, 0.5, "no failures", ha="center", va="center", transform=axs[0][0].transAxes)
    n_coll = int(np.sum(rec.outcome[all_bad] == COLLISION))
    caption = (
        f"{len(bad)} of {_plural(len(all_bad), 'failure')} shown ({_plural(n_coll, 'collision')}, "
        f"{_plural(len(all_bad) - n_coll, 'timeout')}; {len(rec)} episodes)"
    )
    _finish_panels(fig, graph, params, title, caption, [rec], bad, rec.outcome[bad])
    return _save(fig, path, dpi=100)


def comparison_scenes(records: Mapping[str, EpisodeRecords], k: int = 3) -> list[int]:
    """k scene indices for a side-by-side figure: scenes where the controllers' outcomes differ first
    (at most k - 1 of them, so that at least one ordinary scene is shown), then the first scenes."""
    outcomes = np.stack([r.outcome for r in records.values()])  # (C, B)
    differ = np.flatnonzero((outcomes != outcomes[:1]).any(axis=0))[: max(k - 1, 0)].tolist()
    rest = [b for b in range(outcomes.shape[1]) if b not in differ]
    return sorted([*differ, *rest[: k - len(differ)]])


def plot_controller_comparison(
    records: Mapping[str, EpisodeRecords],
    scenes: Scenes,
    indices,
    path: str | Path,
    title: str = "",
    graph: FormationGraph | None = None,
    params: FormationParams | None = None,
    presets: Sequence[str] | None = None,
) -> Path:
    """All controllers side by side on the same scenes: one row per scene, one column per controller."""
    params = params or FormationParams()
    graph = graph or params.graph
    indices, names = list(indices), list(records)
    fig, axs = _panels(len(indices), len(names))
    for row, b in enumerate(indices):
        limits = _limits_across(records, scenes, b)
        for col, name in enumerate(names):
            _draw_episode(
                axs[row][col],
                records[name],
                scenes,
                b,
                graph,
                limits=limits,
                params=params,
                title=f"{name}, {scene_label(scenes, b, presets)}",
            )
    shown = np.concatenate([records[n].outcome[indices] for n in names])
    caption = f"{len(names)} controllers on the same {len(indices)} scenes"
    _finish_panels(fig, graph, params, title, caption, list(records.values()), indices, shown)
    return _save(fig, path, dpi=100)


def _limits_across(records: Mapping[str, EpisodeRecords], scenes: Scenes, b: int):
    """One square view of scene b that holds every controller's trajectory."""
    boxes = np.array([np.ravel(_limits(r, scenes, [b])) for r in records.values()])  # (C, 4)
    lo, hi = boxes[:, [0, 2]].min(axis=0), boxes[:, [1, 3]].max(axis=0)
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2
    return (centre[0] - half, centre[0] + half), (centre[1] - half, centre[1] + half)


# What each kind of bench scene set is, for legends (``--scenes`` / ``--unseen`` specs, ``bench.py``).
SCENE_SET_KINDS = {
    "random": "paper-distribution scenes",
    "paper": "paper-distribution scenes",
    "hard": "hard suite (gates, blockers, dense, other goals)",
    "gates": "gates preset (a wall with one gap)",
    "blockers": "blockers preset (an obstacle on the straight line)",
    "dense": "dense preset (8-10 obstacles)",
    "goals": "goals preset (other goals and start headings)",
    "wide": "wide preset (a mix of all presets)",
    "bend": "bend preset (a narrow corridor with a bend)",
    "trap": "trap preset (a U opening toward the team)",
    "crowd": "crowd preset (20-30 small obstacles)",
    "long": "long preset (goals 14-20 m away)",
    "behind": "behind preset (goal behind the start)",
    "structures": "structures (bend, trap, crowd, long, behind)",
    "mixed-hard": "hard presets mixed by seed",
    **{f"level{k}": f"graded level {k}" for k in range(6)},
}


def scene_set_label(spec: str, seed: int = UNSEEN_SEED_START) -> str:
    """What a bench scene set is, e.g. ``"paper-distribution scenes, unseen seeds"`` for ``random:50``
    (``seed`` is the bench's ``--seed``: seeds from ``UNSEEN_SEED_START`` on are in no dataset)."""
    kind = spec.split(":")[0] if ":" in spec else None
    if kind == "dataset":
        return "dataset episodes' scenes"
    if kind not in SCENE_SET_KINDS:
        return f"scenes of {Path(spec).name}"
    seeds = "unseen seeds" if seed >= UNSEEN_SEED_START else f"seeds from {seed}"
    return f"{SCENE_SET_KINDS[kind]}, {seeds}"


def plot_success_rates(
    counts: Mapping[str, Mapping[str, tuple[int, int]]], path: str | Path, title: str = ""
) -> Path:
    """Success rate per controller and scene set, bars with Wilson 95 % intervals.

    Args:
        counts: ``{scene set label: {controller: (successes, episodes)}}``; the legend shows each label
            with its episode count.
    """
    sets = list(counts)
    names = list(dict.fromkeys(c for s in sets for c in counts[s]))
    width = 0.8 / max(len(sets), 1)
    fig, ax = plt.subplots(figsize=(max(5.0, 1.5 * len(names) * max(len(sets), 1) + 1.5), 4.2))
    for k, s in enumerate(sets):
        xs, rates, lows, highs, texts = [], [], [], [], []
        for i, name in enumerate(names):
            if name not in counts[s]:  # say so: an empty slot would read as 0 %
                x = i + (k - (len(sets) - 1) / 2) * width
                ax.text(x, 2, "not run", ha="center", va="bottom", fontsize=7, color="0.45", rotation=90)
                continue
            succ, n = counts[s][name]
            lo, hi = wilson_interval(int(succ), int(n))
            rate = succ / n if n else 0.0
            xs.append(i + (k - (len(sets) - 1) / 2) * width)
            rates.append(100 * rate)
            lows.append(100 * max(rate - lo, 0.0))  # matplotlib refuses a negative error bar
            highs.append(100 * max(hi - rate, 0.0))
            texts.append(f"{100 * rate:.0f} %\n{succ}/{n}")
        n_set = {counts[s][c][1] for c in counts[s]}
        label = f"{s} ({n_set.pop()} episodes)" if len(n_set) == 1 else s
        ax.bar(xs, rates, width * 0.95, yerr=[lows, highs], capsize=4, label=label, color=f"C{k}", alpha=0.85)
        for x, r, up, t in zip(xs, rates, highs, texts, strict=True):
            if r >= 20:  # inside the bar, at its foot, clear of the error bar
                ax.text(x, 2, t, ha="center", va="bottom", fontsize=7, color="white", weight="bold")
            else:  # above the error bar
                ax.text(x, r + up + 2, t, ha="center", va="bottom", fontsize=7)
    ax.set_xticks(range(len(names)), names)
    ax.set(xlabel="controller", ylabel="success rate [%]", ylim=(0, 122))
    ax.set_yticks(range(0, 101, 20))
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8, loc="upper center", ncol=len(sets), frameon=False)
    ax.set_title(
        f"{title}: success with Wilson 95 % intervals" if title else "success with Wilson 95 % intervals"
    )
    fig.tight_layout()
    return _save(fig, path)
