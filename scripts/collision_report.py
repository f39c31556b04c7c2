"""Where a diffusion controller collides on a level: which agent, against which obstacle, how fast,
and how long the team had already been that close.

    python scripts/collision_report.py --policy.path pretrained/formation_diffusion_safe \
        --level level4 --scenes 100 [--seed 5000000] [--controller diffusion-safe] \
        [--safety-margin 0.11] [--layer-ignores-noise] [--layer-ignores-motion] \
        [--route-proposal on|off] [--route-lookahead N] [--coherence W] [--proposal-blend M]

The controller is the bench's (``bench.controllers.make_controller``, the safety layer told the
level's conditions as the bench tells it); ``--safety-margin`` replaces the checkpoint's margin,
``--layer-ignores-noise`` does not tell the layer the sensing noise (no smoothing: the layer
before 2026-12-04), ``--layer-ignores-motion`` does not tell it that obstacles move; ``--route-proposal`` and
``--route-lookahead`` replace the checkpoint's ``safety_route_proposal`` / ``safety_route_lookahead``
(``off`` and 0: the layer before 2026-12-04 night), ``--coherence`` its ``safety_coherence`` (0: the
layer before 2026-12-04 late), ``--proposal-blend`` its ``safety_proposal_blend`` (0: the layer before
2026-12-05). One
line per collision: the episode, the step, the agent (0-1 leaders, 2-3 followers) and how deep it
is in [mm], the followers' distance from their template slots, the midpoint's speed, the smallest
agent clearance over the 10 and 30 steps before, and the obstacle's rank among the midpoint's
nearest (the ``nearest`` encoding observes 12). The last line is the summary: success %,
collisions, timeouts, and how many collisions came after the team was already within 2 cm of an
obstacle in the 10 steps before (grazes, not run-ins), how many were with a moving obstacle (its
line gives that obstacle's speed over the last step and the part of it towards the agent it hit), and
the mean jerk and control smoothness of the successful episodes (``core.metrics``).
``--controller pac-privileged`` (no checkpoint) reports the privileged expert, on the true world.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402

from lerobot_formation.core.levels import TUNING_SEED_START  # noqa: E402
from lerobot_formation.threads import add_threads_argument, apply_threads  # noqa: E402


def collision_lines(rec, scenes, params) -> tuple[list[str], int, int]:
    """One line per collision of the records ``rec`` (module docstring), how many came after the
    team was within 2 cm in the 10 steps before, and how many were with a moving obstacle."""
    from lerobot_formation.core.dynamics import desired_follower_positions
    from lerobot_formation.core.geometry import agent_clearances
    from lerobot_formation.core.rollout import COLLISION

    lines, dwelt, movers = [], 0, 0
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
        lines.append(
            f"episode {b} step {t}: agent {agent} {-1e3 * gaps[agent]:.1f} mm deep, followers off their "
            f"slots {off[0]:.3f} / {off[1]:.3f} m, speed {speed:.2f} m/s, closest before {before[0]:.3f} m "
            f"(10 steps) / {before[1]:.3f} m (30), obstacle rank {rank}, radius {obstacles[hit, 2]:.2f} m{mover}"
        )
    return lines, dwelt, movers


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--policy.path", dest="policy_path", default=None, help="for the diffusion controllers")
    ap.add_argument("--level", required=True, help="level0 .. level5")
    ap.add_argument("--scenes", type=int, default=100)
    ap.add_argument("--seed", type=int, default=TUNING_SEED_START, help="first scene seed (tuning seeds)")
    ap.add_argument("--controller", default="diffusion-safe")
    ap.add_argument("--candidates", type=int, default=10)
    ap.add_argument("--safety-margin", type=float, default=None)
    ap.add_argument("--layer-ignores-noise", action="store_true")
    ap.add_argument("--layer-ignores-motion", action="store_true")
    ap.add_argument("--route-proposal", choices=("on", "off"), default=None)
    ap.add_argument(
        "--route-lookahead", type=int, default=None, help="steps of route pursuit after each chunk"
    )
    ap.add_argument(
        "--coherence", type=float, default=None, help="best-of-K's weight on keeping to the plan [m]"
    )
    ap.add_argument(
        "--proposal-blend",
        type=int,
        default=None,
        help="steps over which route pursuit's proposal is blended in",
    )
    ap.add_argument("--max-steps", type=int, default=None, help="episode length (default: the env's)")
    add_threads_argument(ap, "torch threads")
    args = ap.parse_args(argv)
    apply_threads(args.threads)

    from lerobot_formation.bench.controllers import make_controller, needs_policy
    from lerobot_formation.bench.scene_sets import level_scenes
    from lerobot_formation.bench.settings import ControllerOptions
    from lerobot_formation.core.dynamics import FormationParams
    from lerobot_formation.core.levels import get_level
    from lerobot_formation.core.metrics import episode_metrics
    from lerobot_formation.core.rollout import COLLISION, SUCCESS, TIMEOUT, rollout

    level = get_level(args.level)  # a bad name: ValueError naming the choices
    if needs_policy(args.controller) and not args.policy_path:
        ap.error(f"--controller {args.controller} needs --policy.path")
    overrides = {}
    if args.safety_margin is not None:
        overrides["safety_margin"] = args.safety_margin
    if args.layer_ignores_noise:
        overrides.update(safety_obstacle_noise=0.0, safety_pose_noise=0.0)
    if args.layer_ignores_motion:
        overrides["safety_moving_obstacles"] = False
    if args.route_proposal is not None:
        overrides["safety_route_proposal"] = args.route_proposal == "on"
    if args.route_lookahead is not None:
        overrides["safety_route_lookahead"] = args.route_lookahead
    if args.coherence is not None:
        overrides["safety_coherence"] = args.coherence
    if args.proposal_blend is not None:
        overrides["safety_proposal_blend"] = args.proposal_blend
    params = FormationParams()
    options = ControllerOptions(
        policy_path=args.policy_path,
        candidates=args.candidates,
        conditions=level.conditions,
        overrides=overrides,
    )
    controller = make_controller(args.controller, params, options)
    scenes = level_scenes(level.name, args.scenes, seed=args.seed)
    rec = rollout(scenes, controller, params, max_steps=args.max_steps, conditions=level.conditions)
    lines, dwelt, movers = collision_lines(rec, scenes, params)
    print("\n".join(lines))
    n = len(scenes)
    ok = rec.outcome == SUCCESS
    per = episode_metrics(rec, scenes.start, scenes.goal)
    motion = "no successful episode"
    if ok.any():
        motion = (
            f"jerk {np.mean(per['jerk'][ok]):.3f}, smoothness {np.mean(per['control_smoothness'][ok]):.3f}"
        )
    print(
        f"{args.controller} on {level.name} ({n} scenes from seed {args.seed}): success "
        f"{100 * np.mean(ok):.1f} %, collisions {int(np.sum(rec.outcome == COLLISION))}, "
        f"timeouts {int(np.sum(rec.outcome == TIMEOUT))}; {dwelt} collisions within 2 cm already in the 10 steps "
        f"before; {movers} with a moving obstacle; {motion}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
