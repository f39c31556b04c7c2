"""Env stepping: FormationVectorEnv (B scenes in one NumPy call) vs a per-scene loop of FormationEnv,
and the cost of the realistic conditions: the vector env with every condition on vs all off.

Both include the followers' 1 ms sub-stepping (100 inner steps per 0.1 s control step), the
observation and the collision/success checks. "Every condition on" is sensing range, obstacle and
pose noise, action noise and delay, both rate limits and moving obstacles (``ALL_ON``), with the same
actions and the same obstacle encoding as "off". Run: ``python benchmarks/bench_env_step.py``
(``--skip-loop``: only the conditions comparison; ``--batch 4 --steps 2 --repeats 1`` is a smoke run).
The last line is the conditions figure: step cost with every condition on / off (target <= 1.5x).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from lerobot_formation.core.perception.conditions import Conditions
from lerobot_formation.envs.env import FormationEnv
from lerobot_formation.envs.vector_env import FormationVectorEnv

ALL_ON = Conditions(
    sensing_range=3.0,
    obstacle_memory=True,
    obstacle_noise=0.03,
    pose_noise=0.02,
    action_noise=0.1,
    action_delay=2,
    max_linear_accel=1.0,
    max_angular_accel=4.0,
    moving_obstacles=2,
    obstacle_speed=0.3,
)


def vector_steps_per_s(
    B: int, actions: np.ndarray, conditions: Conditions | None, encoding: str, repeats: int
) -> float:
    """Env-steps/s of the vector env (best of ``repeats`` timed runs over the actions, after a warm-up)."""
    best = np.inf
    for _ in range(repeats):
        venv = FormationVectorEnv(B, obstacle_encoding=encoding, conditions=conditions)
        venv.reset(seed=0)
        venv.step(actions[0])  # warm-up
        t0 = time.perf_counter()
        for a in actions:
            venv.step(a)
        best = min(best, time.perf_counter() - t0)
    return B * len(actions) / best


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3, help="timed runs of the conditions comparison (best)")
    ap.add_argument("--encoding", default="grid", help="obstacle encoding of the conditions comparison")
    ap.add_argument("--skip-loop", action="store_true", help="skip the per-scene FormationEnv loop")
    args = ap.parse_args(argv)
    B, T = args.batch, args.steps
    rng = np.random.default_rng(0)
    actions = rng.uniform([0.2, -0.5], [0.6, 0.5], size=(T, B, 2)).astype(np.float32)

    if not args.skip_loop:
        batched = vector_steps_per_s(B, actions, None, "grid", 1)
        envs = [FormationEnv() for _ in range(B)]
        for i, e in enumerate(envs):
            e.reset(seed=i)
        t0 = time.perf_counter()
        for t in range(T):
            for i, e in enumerate(envs):
                _, _, term, trunc, _ = e.step(actions[t, i])
                if term or trunc:
                    e.reset(seed=i)
        looped = B * T / (time.perf_counter() - t0)
        print(f"batched FormationVectorEnv, B={B}: {batched:,.0f} env-steps/s")
        print(f"per-scene loop of FormationEnv, B={B}: {looped:,.0f} env-steps/s")
        print(f"ratio batched / per-scene: {batched / looped:.1f}x")

    off = vector_steps_per_s(B, actions, None, args.encoding, args.repeats)
    on = vector_steps_per_s(B, actions, ALL_ON, args.encoding, args.repeats)
    print(
        f"conditions off, B={B}, {args.encoding}: {off:,.0f} env-steps/s ({1e3 / off * B:.2f} ms per batched step)"
    )
    print(
        f"every condition on, B={B}, {args.encoding}: {on:,.0f} env-steps/s ({1e3 / on * B:.2f} ms per batched step)"
    )
    print(f"conditions on / off step cost: {off / on:.2f}x")


if __name__ == "__main__":
    main()
