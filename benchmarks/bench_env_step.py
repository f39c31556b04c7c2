"""Env stepping: FormationVectorEnv (B scenes in one NumPy call) vs a per-scene loop of FormationEnv.

Both include the followers' 1 ms sub-stepping (100 inner steps per 0.1 s control step), the
observation and the collision/success checks. Run: ``python benchmarks/bench_env_step.py``.
The last line is the figure: the speed ratio.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from lerobot_formation.envs.env import FormationEnv
from lerobot_formation.envs.vector_env import FormationVectorEnv


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--steps", type=int, default=20)
    args = ap.parse_args()
    B, T = args.batch, args.steps
    rng = np.random.default_rng(0)
    actions = rng.uniform([0.2, -0.5], [0.6, 0.5], size=(T, B, 2)).astype(np.float32)

    venv = FormationVectorEnv(B)
    venv.reset(seed=0)
    venv.step(actions[0])  # warm-up
    t0 = time.perf_counter()
    for t in range(T):
        venv.step(actions[t])
    batched = B * T / (time.perf_counter() - t0)

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


if __name__ == "__main__":
    main()
