"""Observation cost of the route hint: one ``FormationEnv`` control step at B = 1 observing ``nearest+route``
against the same step observing ``nearest`` (the baseline), on the same scenes and actions.

The route hint (``core/encodings/route_encoding.py``) needs a grid cost-to-go of the observed scene. It is built
once per distinct observed scene (cached by ``navigation.SceneFields``), so the first step of an episode
pays for it and later steps cost a few look-ups. Both are reported: the reset (first observation) and the
median step, each with its ratio to ``nearest``. A step includes the followers' 100 sub-steps of 1 ms, so
the step ratio is what a deployed robot pays per 0.1 s control period.

    python benchmarks/bench_route_encoding.py --scenes 20 --steps 100

The last line is the figure: the median step time with the route hint, and its ratio to ``nearest``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from lerobot_formation.core.world.sampling import UNSEEN_SEED_START
from lerobot_formation.envs.env import FormationEnv


def run(encoding: str, seeds: list[int], actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reset and step times (s) of one env observing ``encoding``: (len(seeds),), (len(seeds) * steps,)."""
    env = FormationEnv(obstacle_encoding=encoding)
    resets, steps = [], []
    for i, seed in enumerate(seeds):
        t0 = time.perf_counter()
        env.reset(seed=seed)
        resets.append(time.perf_counter() - t0)
        for a in actions[i]:
            t0 = time.perf_counter()
            _, _, terminated, truncated, _ = env.step(a)
            steps.append(time.perf_counter() - t0)
            if terminated or truncated:
                break
    return np.array(resets), np.array(steps)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", type=int, default=20, help="unseen paper-layout scenes (seeds 1,000,000+)")
    ap.add_argument("--steps", type=int, default=100, help="control steps per scene at most")
    args = ap.parse_args(argv)
    if args.scenes < 1 or args.steps < 1:
        raise ValueError(f"--scenes and --steps must be >= 1, got {args.scenes}, {args.steps}")
    seeds = list(range(UNSEEN_SEED_START, UNSEEN_SEED_START + args.scenes))
    rng = np.random.default_rng(0)
    actions = rng.uniform([0.2, -0.3], [0.5, 0.3], size=(args.scenes, args.steps, 2)).astype(np.float32)
    # Warm-up (imports, first allocations) on a scene outside the timed ones, so that every timed scene
    # still pays for its own cost-to-go field once.
    run("nearest+route", [UNSEEN_SEED_START - 1], actions[:1])
    base_reset, base_step = run("nearest", seeds, actions)
    route_reset, route_step = run("nearest+route", seeds, actions)
    print(f"{args.scenes} unseen scenes, up to {args.steps} steps each; B = 1, one FormationEnv per encoding")
    for name, reset, step in (("nearest", base_reset, base_step), ("nearest+route", route_reset, route_step)):
        print(
            f"  {name:14s} reset median {1e3 * np.median(reset):7.2f} ms (max {1e3 * reset.max():7.2f}); "
            f"step median {1e3 * np.median(step):6.3f} ms, 90th percentile {1e3 * np.percentile(step, 90):6.3f} ms "
            f"({len(step)} steps)"
        )
    print(f"reset ratio route / nearest: {np.median(route_reset) / np.median(base_reset):.2f}x")
    print(
        f"step with the route hint: {1e3 * np.median(route_step):.3f} ms median, "
        f"{np.median(route_step) / np.median(base_step):.2f}x the nearest step"
    )


if __name__ == "__main__":
    main()
