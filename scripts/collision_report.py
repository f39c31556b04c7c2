"""Where a diffusion controller collides on a level: which agent, against which obstacle, how fast,
and how long the team had already been that close.

    python scripts/collision_report.py --policy.path pretrained/formation_diffusion_safe \
        --level level4 --scenes 100 [--seed 5000000] [--controller diffusion-safe] \
        [--safety-margin 0.11] [--follower-margin 0.03] [--layer-ignores-noise] [--layer-ignores-motion] \
        [--route-proposal on|off] [--route-lookahead N] [--coherence W] [--proposal-blend M] \
        [--halt-lookahead N]

The controller is the bench's (``bench.controllers.make_controller``, the safety layer told the
level's conditions as the bench tells it); ``--safety-margin`` replaces the checkpoint's margin
(``--follower-margin`` its ``safety_follower_margin``),
``--layer-ignores-noise`` does not tell the layer the sensing noise (no smoothing: the layer
before 2026-12-04), ``--layer-ignores-motion`` does not tell it that obstacles move; ``--route-proposal`` and
``--route-lookahead`` replace the checkpoint's ``safety_route_proposal`` / ``safety_route_lookahead``
(``off`` and 0: the layer before 2026-12-04 night), ``--coherence`` its ``safety_coherence`` (0: the
layer before 2026-12-04 late), ``--proposal-blend`` its ``safety_proposal_blend`` (0: the layer before
2026-12-05), ``--chunk-smoothing`` its ``chunk_smoothing`` (0: before 2026-12-05, evening),
``--halt-lookahead`` its ``safety_halt_lookahead`` (0: before 2026-12-06); these flags are ``bench.level_report``'s, shared with ``scripts/jerk_sources.py``. One
line per collision: the episode, the step, the agent (0-1 leaders, 2-3 followers) and how deep it
is in [mm], the followers' distance from their template slots, the midpoint's speed, the smallest
agent clearance over the 10 and 30 steps before, and the obstacle's rank among the midpoint's
nearest (the ``nearest`` encoding observes 12). The last line is the summary (``bench.level_report``): success %,
collisions, timeouts, and how many collisions came after the team was already within 2 cm of an
obstacle in the 10 steps before (grazes, not run-ins), how many were with a moving obstacle (its
line gives that obstacle's speed over the last step and the part of it towards the agent it hit) and
how many of those struck a team that was not closing on the mover (``core.metrics.mover_strikes``), and
the mean jerk and control smoothness of the successful episodes (``core.metrics``).
``--controller pac-privileged`` (no checkpoint) reports the privileged expert, on the true world.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402

from lerobot_formation.threads import add_threads_argument, apply_threads  # noqa: E402


def collision_lines(rec, scenes, params) -> tuple[list[str], int, int, int]:
    """One line per collision of the records ``rec`` (module docstring), how many came after the
    team was within 2 cm in the 10 steps before, how many were with a moving obstacle, and how many
    of those struck a team that was not closing on it (``core.metrics.mover_strikes``)."""
    from lerobot_formation.core.dynamics import desired_follower_positions
    from lerobot_formation.core.geometry import agent_clearances
    from lerobot_formation.core.metrics import mover_strikes
    from lerobot_formation.core.rollout import COLLISION

    lines, dwelt, movers = [], 0, 0
    struck = mover_strikes(rec, scenes.obstacles, scenes.mask, params.agent_radius)
    for b in np.flatnonzero(rec.outcome == COLLISION):
        t = int(rec.steps[b])
        pos = rec.positions[b, t]
        paths = rec.obstacle_paths  # the true centres at every frame under conditions; else static
        now, last = (paths[b, t], paths[b, t - 1]) if paths is not None else (scenes.obstacles[b, :, :2],) * 2
        obstacles = np.concatenate([now, scenes.obstacles[b, :, 2:3]], -1)
        gaps = agent_clearances(pos[None], obstacles[None], params.agent_radius)[0]
        agent = int(np.argmin(gaps))
        reach = np.linalg.norm(pos[agent][None] - obstacles[:, :2], axis=-1) - obstacles[:, 2]
        hit = int(np.argmin(np.where(scenes.mask[b], reach, np.inf)))
        surface = np.linalg.norm(last - rec.poses[b, t - 1, :2], axis=-1) - obstacles[:, 2]
        surface = np.where(scenes.mask[b], surface, np.inf)
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
        if struck[b]:
            mover += ", struck: the team was not closing on it"
        lines.append(
            f"episode {b} step {t}: agent {agent} {-1e3 * gaps[agent]:.1f} mm deep, followers off their "
            f"slots {off[0]:.3f} / {off[1]:.3f} m, speed {speed:.2f} m/s, closest before {before[0]:.3f} m "
            f"(10 steps) / {before[1]:.3f} m (30), obstacle rank {rank}, radius {obstacles[hit, 2]:.2f} m{mover}"
        )
    return lines, dwelt, movers, int(struck.sum())


def main(argv: list[str] | None = None) -> int:
    from lerobot_formation.bench import level_report

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    level_report.add_arguments(ap)
    ap.add_argument("--controller", default="diffusion-safe")
    add_threads_argument(ap, "torch threads")
    args = ap.parse_args(argv)
    apply_threads(args.threads)
    try:
        settings = {k: getattr(args, k) for k in level_report.RUN_FLAGS}
        run = level_report.run_flags(args.controller, **settings)
    except ValueError as e:  # a bad level name, a missing checkpoint path
        ap.error(str(e))
    lines, dwelt, movers, struck = collision_lines(run.records, run.scenes, run.params)
    print("\n".join(lines))
    print(
        run.summary(
            f"{dwelt} collisions within 2 cm already in the 10 steps before; {movers} with a moving obstacle, "
            f"{struck} of them struck while the team was not closing"
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
