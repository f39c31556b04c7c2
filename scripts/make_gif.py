"""An animated GIF of one episode: the four agents (leaders L1, L2, followers F1, F2) with their trails
and the formation's edges, the obstacles (moving ones where they are, with their tracks; obstacles
the team has not sensed yet drawn faint), the goal and its tolerance disc, and the time and outcome.

The episode runs on the bench's engine (``lerobot-formation-bench``: the same scenes, conditions and
controllers), by default the shipped default with its safety layer (``diffusion-safe``) on an unseen
scene of the hardest level (level5's scene 2, seed 1000002: a crowd of obstacles sensed within 3 m,
two of them moving, where PAC and the default without its layer collide). The README's animation
(about 1 MB) was made by::

    python scripts/make_gif.py --out docs/images/episode.gif

(``--policy.path pretrained/formation_diffusion_route_v1 --controller diffusion-safe --scenes level5:3
--scene 2 --every 4`` are the defaults). ``--scenes SET --scene I`` picks scene I of a bench scene set
(its seeds from ``--seed``, default the set's own), ``--max-steps`` cuts the episode short (a timeout
at that step). Frames are every ``--every``-th control step (more when the episode would give more
than ``--max-frames``), drawn by matplotlib at ``--dpi`` and written with its ``PillowWriter``; the last
frame is held for a second. The GIF is written to a temporary file next to ``--out`` and renamed into
place; an existing ``--out`` is refused unless ``--overwrite``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_POLICY = REPO / "pretrained" / "formation_diffusion_route_v1"
AGENT_COLORS = ("tab:blue", "tab:cyan", "tab:orange", "tab:purple")  # as the bench's figures
HOLD_S = 1.0  # [s] the last frame (the outcome) is shown this long


def build_parser() -> argparse.ArgumentParser:
    from lerobot_formation.threads import add_threads_argument

    ap = argparse.ArgumentParser(
        description=__doc__.split("\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        epilog="example: python scripts/make_gif.py --scenes level3:5 --scene 4 --out outputs/level3_4.gif",
    )
    ap.add_argument(
        "--out", required=True, help="the GIF to write (refused if it exists, unless --overwrite)"
    )
    ap.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    ap.add_argument(
        "--policy.path",
        dest="policy_path",
        default=str(DEFAULT_POLICY),
        help="formation_diffusion checkpoint folder (for the controllers that need one)",
    )
    ap.add_argument(
        "--controller", default="diffusion-safe", help="a lerobot-formation-bench controller (pac, mppi, ...)"
    )
    ap.add_argument("--scenes", default="level5:3", help="a lerobot-formation-bench scene set")
    ap.add_argument("--scene", type=int, default=2, help="the index of the episode's scene in --scenes")
    ap.add_argument("--seed", type=int, default=None, help="first seed of --scenes (default: the set's own)")
    ap.add_argument("--seed-policy", type=int, default=0, help="seed of the controller's noise")
    ap.add_argument("--max-steps", type=int, default=None, help="control steps at most (default: the env's)")
    ap.add_argument("--every", type=int, default=4, help="a frame every this many control steps")
    ap.add_argument("--max-frames", type=int, default=150, help="frames at most (--every grows to fit)")
    ap.add_argument("--fps", type=float, default=15.0, help="frames per second of the GIF")
    ap.add_argument("--dpi", type=int, default=100, help="resolution of the frames")
    ap.add_argument("--size", type=float, default=4.8, help="[in] side of the (square) frame")
    add_threads_argument(ap, "torch threads of the diffusion controllers")
    return ap


def run_episode(args):
    """(records of the one episode, its scenes (one), the conditions, the formation params)."""
    import numpy as np

    from lerobot_formation.bench.controllers import make_controller, needs_policy
    from lerobot_formation.bench.scene_sets import parse_scenes, scene_set_conditions, scene_set_level
    from lerobot_formation.bench.settings import ControllerOptions
    from lerobot_formation.core.episodes.rollout import rollout
    from lerobot_formation.core.perception.conditions import Conditions
    from lerobot_formation.core.world.dynamics import FormationParams
    from lerobot_formation.core.world.sampling import UNSEEN_SEED_START

    level = scene_set_level(args.scenes)
    seed = args.seed if args.seed is not None else (level.seed if level is not None else UNSEEN_SEED_START)
    conditions = scene_set_conditions(args.scenes, Conditions())
    scenes = parse_scenes(args.scenes, seed)
    if not 0 <= args.scene < len(scenes):
        raise ValueError(f"--scene {args.scene} is not a scene of {args.scenes} ({len(scenes)} scenes)")
    scenes = scenes[np.array([args.scene])]
    params = FormationParams()
    if args.max_steps is not None:
        params = dataclasses.replace(params, max_steps=args.max_steps)
    moving = scenes.velocities is not None and bool(np.any(scenes.velocities))
    options = ControllerOptions(
        policy_path=args.policy_path if needs_policy(args.controller) else None,
        seed_policy=args.seed_policy,
        conditions=conditions,
        scenes_move=moving,
    )
    controller = make_controller(args.controller, params, options)
    rec = rollout(scenes, controller, params, conditions=conditions)
    return rec, scenes, conditions, params


def frame_steps(n_steps: int, every: int, max_frames: int) -> list[int]:
    """The control steps drawn: 0, every, 2 every, ... and the last one (``n_steps``), at most
    ``max_frames`` of them (the stride grows to fit)."""
    stride = max(every, -(-n_steps // max(max_frames - 1, 1)))
    steps = list(range(0, n_steps, stride))
    return steps + [n_steps]


def draw_gif(rec, scenes, params, title: str, path: Path, args) -> int:
    """Write the animation of episode 0 of ``rec`` to ``path``; returns the number of frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from matplotlib.animation import FuncAnimation, PillowWriter
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    from lerobot_formation.core.episodes.rollout import OUTCOME_NAMES

    n = int(rec.steps[0])
    pos = rec.positions[0, : n + 1]  # (T + 1, N, 2)
    paths = rec.obstacle_paths[0, : n + 1] if rec.obstacle_paths is not None else None  # (T + 1, M, 2)
    seen = rec.seen_step[0] if rec.seen_step is not None else None  # (M,)
    obstacles, mask = scenes.obstacles[0], scenes.mask[0]
    graph = params.graph
    steps = frame_steps(n, args.every, args.max_frames)
    hold = max(1, round(HOLD_S * args.fps))
    frames = steps + [n] * hold

    # the view: everything the episode shows, square
    pts = [
        pos.reshape(-1, 2),
        scenes.goal[:1],
        obstacles[mask, :2] - obstacles[mask, 2:],
        obstacles[mask, :2] + obstacles[mask, 2:],
    ]
    if paths is not None:
        track = paths[:, mask].reshape(-1, 2)
        pts.append(track[np.isfinite(track).all(axis=1)])
    pts = np.concatenate([p[np.isfinite(p).all(axis=1)] for p in pts])
    lo, hi = pts.min(axis=0) - 0.5, pts.max(axis=0) + 0.5
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2

    fig, ax = plt.subplots(figsize=(args.size, args.size + 0.45))
    fig.subplots_adjust(left=0.12, right=0.97, top=0.92, bottom=0.17)
    ax.set_aspect("equal")
    ax.set(xlim=(centre[0] - half, centre[0] + half), ylim=(centre[1] - half, centre[1] + half))
    ax.set(xlabel="x [m]", ylabel="y [m]")
    ax.tick_params(labelsize=7)
    ax.add_patch(
        plt.Circle(tuple(scenes.goal[0]), params.goal_tolerance, color="tab:green", alpha=0.25, zorder=1)
    )
    ax.plot(*scenes.goal[0], "*", color="tab:green", ms=12, zorder=3)
    moves = np.zeros(len(obstacles), dtype=bool)
    if paths is not None:
        for m in np.flatnonzero(mask):
            track = paths[:, m][np.isfinite(paths[:, m]).all(axis=1)]
            moves[m] = len(track) > 1 and np.ptp(track, axis=0).max() > 1e-9
    discs, tracks = {}, {}
    for m in np.flatnonzero(mask):
        x, y, r = obstacles[m]
        discs[m] = ax.add_patch(plt.Circle((x, y), r, color="0.6", zorder=1))
        if moves[m]:
            (tracks[m],) = ax.plot([], [], ":", color="tab:brown", lw=1.2, zorder=1)
    trails = [ax.plot([], [], color=AGENT_COLORS[a % 4], lw=1.3, zorder=2)[0] for a in range(pos.shape[1])]
    edges = [ax.plot([], [], color="k", lw=0.8, zorder=3)[0] for _ in graph.edge_i]
    agents = ax.scatter(
        pos[0, :, 0],
        pos[0, :, 1],
        s=28,
        c=[AGENT_COLORS[a % 4] for a in range(pos.shape[1])],
        edgecolors="k",
        linewidths=0.5,
        zorder=4,
    )
    clock = ax.text(
        0.02,
        0.97,
        "",
        transform=ax.transAxes,
        va="top",
        fontsize=9,
        bbox=dict(fc="white", ec="0.7", alpha=0.85),
    )
    outcome = OUTCOME_NAMES[int(rec.outcome[0])]
    handles = [
        Line2D([], [], color=AGENT_COLORS[a % 4], marker="o", mec="k", label=name)
        for a, name in enumerate(graph.agents)
    ]
    handles += [
        Patch(color="0.6", label="obstacle"),
        Line2D([], [], color="tab:green", marker="*", ls="", ms=10, label="goal"),
    ]
    if seen is not None:
        handles.append(Patch(color="0.6", alpha=0.25, label="not sensed yet"))
    if moves.any():
        handles.append(Line2D([], [], color="tab:brown", ls=":", label="moving obstacle's track"))
    fig.legend(handles=handles, loc="lower center", ncol=4, fontsize=7, frameon=False)
    fig.suptitle(title, fontsize=9)

    def update(t: int):
        for m, disc in discs.items():
            if paths is not None and np.isfinite(paths[t, m]).all():
                disc.set_center(tuple(paths[t, m]))
            sensed = seen is None or 0 <= seen[m] <= t
            disc.set_alpha(1.0 if sensed else 0.25)
        for m, line in tracks.items():
            line.set_data(paths[: t + 1, m, 0], paths[: t + 1, m, 1])
        for a, line in enumerate(trails):
            line.set_data(pos[: t + 1, a, 0], pos[: t + 1, a, 1])
        for line, i, j in zip(edges, graph.edge_i, graph.edge_j, strict=True):
            line.set_data(pos[t, [i, j], 0], pos[t, [i, j], 1])
        agents.set_offsets(pos[t])
        text = f"t = {t * rec.dt:4.1f} s"
        if t == n:
            text += f": {outcome}"
        clock.set_text(text)
        return []

    writer = PillowWriter(fps=args.fps)
    FuncAnimation(fig, update, frames=frames, blit=False).save(str(path), writer=writer, dpi=args.dpi)
    plt.close(fig)
    return len(frames)


def write_atomically(out: Path, overwrite: bool, draw) -> None:
    """``draw(tmp)`` writes a temporary GIF next to ``out``, which then takes its place: renamed over it
    with ``overwrite``, else linked (which fails if ``out`` appeared meanwhile)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{out.stem}.", suffix=".gif", dir=out.parent)
    os.close(fd)
    tmp = Path(name)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # as an ordinary new file (mkstemp makes it private)
    try:
        draw(tmp)
        if overwrite:
            os.replace(tmp, out)
        else:
            os.link(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    out = Path(args.out)
    if out.suffix.lower() != ".gif":
        ap.error(f"--out must name a .gif file, got {out}")
    if out.exists() and not args.overwrite:
        ap.error(f"--out {out} exists; add --overwrite to replace it")
    for flag, value, least in (
        ("--every", args.every, 1),
        ("--max-frames", args.max_frames, 2),
        ("--dpi", args.dpi, 10),
    ):
        if value < least:
            ap.error(f"{flag} must be >= {least}, got {value}")
    if args.max_steps is not None and args.max_steps < 1:
        ap.error(f"--max-steps must be >= 1, got {args.max_steps}")
    if args.fps <= 0:
        ap.error(f"--fps must be > 0, got {args.fps}")
    from lerobot_formation.bench.controllers import controller_names
    from lerobot_formation.threads import apply_threads

    if args.controller not in controller_names():
        ap.error(f"unknown --controller {args.controller!r}; choose from {', '.join(controller_names())}")
    apply_threads(args.threads)
    try:
        rec, scenes, conditions, params = run_episode(args)
    except ValueError as e:
        ap.error(str(e))
    from lerobot_formation.core.episodes.rollout import OUTCOME_NAMES

    seed = int(scenes.seeds[0])
    outcome = OUTCOME_NAMES[int(rec.outcome[0])]
    where = f"{args.scenes.split(':')[0]} scene {args.scene}" + (f" (seed {seed})" if seed >= 0 else "")
    from lerobot_formation.bench.demo import LABELS

    name = f"{LABELS[args.controller]} ({args.controller})" if args.controller in LABELS else args.controller
    title = f"{name}\n{where}: {outcome} after {int(rec.steps[0]) * rec.dt:.1f} s"
    frames = []
    write_atomically(
        out, args.overwrite, lambda tmp: frames.append(draw_gif(rec, scenes, params, title, tmp, args))
    )
    size = out.stat().st_size
    print(f"{title.replace(chr(10), ', ')}; conditions: {conditions.changed() or 'none'}")
    print(f"wrote {out}: {frames[0]} frames at {args.fps:g} fps, {size / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
