"""Where a diffusion controller collides on a level: which agent, against which obstacle, how fast,
and how long the team had already been that close.

    python scripts/collision_report.py --policy.path pretrained/formation_diffusion_route_v1 \
        --level level4 --scenes 100 [--seed 5000000] [--controller diffusion-safe] \
        [--safety-margin 0.11] [--horizon N] [--chunk-smoothing N] [--mover-uncertainty U] \
        [--layer-ignores-noise] [--layer-ignores-motion] [--trace EPISODE ...] [--trace-steps N]

The controller is the bench's (``bench.controllers.make_controller``, the safety layer told the
level's conditions as the bench tells it); ``--safety-margin`` replaces the checkpoint's
``safety_margin``, ``--horizon`` its ``safety_horizon`` (0: the chunk alone), ``--chunk-smoothing``
its ``chunk_smoothing``, ``--mover-uncertainty`` its ``safety_mover_uncertainty``;
``--layer-ignores-noise`` does not tell the layer the level's sensing noise (no smoothing),
``--layer-ignores-motion`` does not tell it that obstacles move (its ``safety_world``); these flags
are ``bench.level_report``'s, shared with ``scripts/jerk_sources.py``. One
line per collision: the episode, the step, the agent (0-1 leaders, 2-3 followers) and how deep it
is in [mm], the followers' distance from their template slots, the midpoint's speed, the smallest
agent clearance over the 10 and 30 steps before, and the obstacle's rank among the midpoint's
nearest (the ``nearest`` encoding observes 12). The last line is the summary (``bench.level_report``): success %,
collisions, timeouts, and how many collisions came after the team was already within 2 cm of an
obstacle in the 10 steps before (grazes, not run-ins), how many were with a moving obstacle (its
line gives that obstacle's speed over the last step, the part of it towards the agent it hit and, on
a level with a sensing range, how long before the contact the team first sensed it) and
how many of those struck a team that was not closing on the mover (``core.episodes.metrics.mover_strikes``), and
the mean jerk and control smoothness of the successful episodes (``core.episodes.metrics``).
``--controller pac-privileged`` (no checkpoint) reports the privileged expert, on the true world.

``--trace EPISODE ...`` then prints the last ``--trace-steps`` steps (default 30) of those episodes
(their numbers in this run, as the collision lines give them), one line a step (``trace_lines``): the
midpoint pose, the command sent and the one executed, the team's smallest gap and to which obstacle,
the nearest moving obstacle (its gap, where it is in the team's frame, its speed and how much of it
comes towards the team) and, for a controller with a safety layer, what the layer did at that step
(``bench.level_report.recording_replanner``): a replan (cut: the recheck or the filter ended the
plan early), how many of the scored chunks were safe, and what it kept (a sample, route pursuit's
proposal, a path of the lattice search, an escape manoeuvre, or the fallback where nothing was safe), and whether the filter
changed the command. An episode's outcome depends on the batch it ran in (the noise is drawn for
the whole batch), so a trace is of this run's episode: the same flags give it again.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402

from lerobot_formation.threads import add_threads_argument, apply_threads  # noqa: E402


def collision_lines(rec, scenes, params, sensed: bool = False) -> tuple[list[str], int, int, int]:
    """One line per collision of the records ``rec`` (module docstring), how many came after the
    team was within 2 cm in the 10 steps before, how many were with a moving obstacle, and how many
    of those struck a team that was not closing on it (``core.episodes.metrics.mover_strikes``). With
    ``sensed`` (the run had a sensing range), a mover's line says how long before the contact the
    team first observed it (``EpisodeRecords.seen_step``: some agent came within the range of it)."""
    from lerobot_formation.core.episodes.metrics import mover_strikes
    from lerobot_formation.core.episodes.rollout import COLLISION
    from lerobot_formation.core.world.dynamics import desired_follower_positions

    lines, dwelt, movers = [], 0, 0
    struck = mover_strikes(rec, scenes.obstacles, scenes.mask, params.agent_radius)
    for b in np.flatnonzero(rec.outcome == COLLISION):
        t = int(rec.steps[b])
        pos = rec.positions[b, t]
        paths = rec.obstacle_paths  # the true centres at every frame under conditions; else static
        now, last = (paths[b, t], paths[b, t - 1]) if paths is not None else (scenes.obstacles[b, :, :2],) * 2
        obstacles = np.concatenate([now, scenes.obstacles[b, :, 2:3]], -1)
        gap = agent_obstacle_gaps(pos, obstacles, scenes.mask[b], params.agent_radius)
        agent, hit = (int(i) for i in np.unravel_index(np.argmin(gap), gap.shape))
        # the midpoint's gap to each obstacle's surface a step before: the rank the encoding sees
        before_step = np.concatenate([last, obstacles[:, 2:]], -1)
        surface = agent_obstacle_gaps(rec.poses[b, t - 1, None, :2], before_step, scenes.mask[b], 0.0)[0]
        rank = int((surface < surface[hit]).sum())
        slots = desired_follower_positions(rec.poses[b, t], params.graph)
        off = np.linalg.norm(pos[2:] - slots, axis=-1)
        speed = np.linalg.norm(rec.poses[b, t, :2] - rec.poses[b, t - 1, :2]) / params.dt
        before = [float(np.nanmin(rec.agent_clearance[b, max(0, t - k) : t])) for k in (10, 30)]
        dwelt += int(before[0] < 0.02)
        # the obstacle's own speed over the last step, and its part towards the agent it hit
        step = (now[hit] - last[hit]) / params.dt
        to_agent = pos[agent] - now[hit]
        closing = float(step @ to_agent / max(np.linalg.norm(to_agent), 1e-9))
        moving = bool(np.linalg.norm(step) > 1e-6)
        movers += int(moving)
        mover = f", a mover at {np.linalg.norm(step):.2f} m/s ({closing:+.2f} towards it)" if moving else ""
        if moving and sensed:
            mover += f", sensed {(t - max(int(rec.seen_step[b, hit]), 0)) * params.dt:.1f} s before"
        if struck[b]:
            mover += ", struck: the team was not closing on it"
        lines.append(
            f"episode {b} step {t}: agent {agent} {-1e3 * gap[agent, hit]:.1f} mm deep, followers off their "
            f"slots {off[0]:.3f} / {off[1]:.3f} m, speed {speed:.2f} m/s, closest before {before[0]:.3f} m "
            f"(10 steps) / {before[1]:.3f} m (30), obstacle rank {rank}, radius {obstacles[hit, 2]:.2f} m{mover}"
        )
    return lines, dwelt, movers, int(struck.sum())


def agent_obstacle_gaps(positions, obstacles, mask, agent_radius) -> np.ndarray:
    """(N, M) the gap between each agent disc at positions (N, 2) and each obstacle (M, 3) of one
    episode, inf where ``mask`` (M,) says there is none."""
    from lerobot_formation.core.world.geometry import obstacle_gaps

    gap = obstacle_gaps(positions[None], obstacles[None])[0] - agent_radius
    return np.where(mask[None], gap, np.inf)


# what a replan kept, other than one of the samples, the first that applies (``bench.level_report.EVENTS``;
# the fallback keeps the widest candidate, which may be a manoeuvre or the proposal)
KEPT = (
    ("fallback", "the fallback"),
    ("escape", "an escape"),
    ("proposal", "the proposal"),
    ("search", "a search path"),
)


def trace_lines(rec, scenes, params, b: int, steps: int = 30, recorder=None) -> list[str]:
    """The last ``steps`` steps of episode ``b`` of the records ``rec``, one line a step (module
    docstring); ``recorder``: the run's ``bench.level_report.recording_replanner``, or None."""
    n = int(rec.steps[b])
    paths = rec.obstacle_paths  # the true centres at every frame under conditions; else static
    real = scenes.mask[b]
    radius = scenes.obstacles[b, :, 2]
    lines = []
    for t in range(max(0, n - steps), n + 1):
        centres = paths[b, t] if paths is not None else scenes.obstacles[b, :, :2]
        later = paths[b, min(t + 1, n)] if paths is not None else centres
        earlier = paths[b, max(t - 1, 0)] if paths is not None else centres
        velocity = (later - earlier) / (params.dt * max(min(t + 1, n) - max(t - 1, 0), 1))  # (M, 2)
        pos = rec.positions[b, t]  # (N, 2)
        gap = agent_obstacle_gaps(
            pos, np.concatenate([centres, radius[:, None]], -1), real, params.agent_radius
        )
        agent, hit = np.unravel_index(np.argmin(gap), gap.shape)
        x, y, phi = rec.poses[b, t]
        line = f"step {t:4d} pose ({x:6.2f}, {y:6.2f}, {np.degrees(phi) % 360:5.1f} deg)"
        if t < n:
            sent = rec.commands[b, t] if rec.commands is not None else rec.actions[b, t]
            ran = rec.actions[b, t]
            line += f" sent ({sent[0]:.2f}, {sent[1]:+.2f}) ran ({ran[0]:.2f}, {ran[1]:+.2f})"
        line += f" | gap {gap[agent, hit]:+.3f} m (agent {agent}, obstacle {hit})"
        moving = real & (np.linalg.norm(velocity, axis=-1) > 1e-6)
        if moving.any():
            m = int(np.argmin(np.where(moving, gap.min(axis=0), np.inf)))
            near = int(np.argmin(gap[:, m]))
            ahead = np.array([np.cos(phi), np.sin(phi)])
            right = np.array([np.sin(phi), -np.cos(phi)])
            off = centres[m] - rec.poses[b, t, :2]
            to_agent = pos[near] - centres[m]
            closing = float(velocity[m] @ to_agent / max(np.linalg.norm(to_agent), 1e-9))
            line += (
                f" | mover {m}: gap {gap[near, m]:+.3f} m, {off @ ahead:+.2f} m ahead {off @ right:+.2f} m right,"
                f" {np.linalg.norm(velocity[m]):.2f} m/s ({closing:+.2f} towards agent {near})"
            )
        if recorder is not None and t < n:
            line += " | " + layer_note(recorder, b, t)
        lines.append(line)
    return lines


def layer_note(recorder, b: int, t: int) -> str:
    """What the safety layer did at step t of episode b (``trace_lines``)."""
    events = recorder.events
    parts = []
    if events["replan"][b, t] or events["replan_cut"][b, t]:
        kind = "replan" if events["replan"][b, t] else "replan (cut)"
        if recorder.scored[b, t] >= 0:  # best-of-K scored the chunks (with one sample it does not)
            kept = next((text for name, text in KEPT if events[name][b, t]), "a sample")
            kind += f": {recorder.safe_count[b, t]} of {recorder.scored[b, t]} safe, kept {kept}"
        parts.append(kind)
    if events["filter"][b, t]:
        parts.append("filtered")
    return "; ".join(parts) or "running on"


def main(argv: list[str] | None = None) -> int:
    from lerobot_formation.bench import level_report
    from lerobot_formation.bench.controllers import runs_replanner
    from lerobot_formation.core.episodes.levels import get_level
    from lerobot_formation.core.episodes.rollout import COLLISION, SUCCESS

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    level_report.add_arguments(ap)
    ap.add_argument("--controller", default="diffusion-safe")
    ap.add_argument(
        "--trace", type=int, nargs="+", default=(), metavar="EPISODE", help="episodes to print step by step"
    )
    ap.add_argument("--trace-steps", type=int, default=30, help="the last steps of each traced episode")
    add_threads_argument(ap, "torch threads")
    args = ap.parse_args(argv)
    apply_threads(args.threads)
    try:
        settings = {k: getattr(args, k) for k in level_report.RUN_FLAGS}
        bad = [e for e in args.trace if not 0 <= e < args.scenes]
        if bad:
            raise ValueError(f"--trace takes episodes 0 .. {args.scenes - 1} of this run, got {bad}")
        if args.trace_steps < 1:
            raise ValueError(f"--trace-steps must be >= 1, got {args.trace_steps}")
        layer = bool(args.trace) and runs_replanner(args.controller)  # a replanner to record
        wrap = level_report.recording_replanner if layer else None
        run = level_report.run_flags(args.controller, wrap, **settings)
    except ValueError as e:  # a bad level name, a missing checkpoint path, a bad trace
        ap.error(str(e))
    sensed = get_level(args.level).conditions.sensing_range is not None  # the name passed run_flags
    lines, dwelt, movers, struck = collision_lines(run.records, run.scenes, run.params, sensed)
    print("\n".join(lines))
    recorder = run.controller.replanner if layer else None
    for b in args.trace:
        outcome = {SUCCESS: "success", COLLISION: "collision"}.get(int(run.records.outcome[b]), "timeout")
        print(f"episode {b} ({outcome} after {int(run.records.steps[b])} steps):")
        print("\n".join(trace_lines(run.records, run.scenes, run.params, b, args.trace_steps, recorder)))
    print(
        run.summary(
            f"{dwelt} collisions within 2 cm already in the 10 steps before; {movers} with a moving obstacle, "
            f"{struck} of them struck while the team was not closing"
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
