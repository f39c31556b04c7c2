"""Formation-error floor of the follower law: the paper's sign() against the boundary-layer variant,
and the cost of one 0.1 s control step (B = 256 teams) for each inner step.

From the paper's start with the leaders still, and with the leaders driving a curve
(v = 0.4 m/s, omega = 0.3 rad/s), the floor is the mean formation error e_d from t = 2 s to 10 s.
Run: ``python benchmarks/bench_follower_floor.py`` (``--steps``, ``--batch`` and ``--repeats`` make it
smaller: ``--steps 21 --batch 2 --repeats 1`` is a smoke run). The last line is the figure: the floor
ratio sign() / boundary layer at 1 ms, at the same cost per step.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from lerobot_formation.core.world.dynamics import (
    FormationParams,
    agent_positions,
    formation_error,
    initial_state,
    step,
)

SETTLE = 20  # control steps (2 s) before the floor is measured


def floor(params: FormationParams, action, steps: int = 100) -> float:
    """Mean formation error from t = 2 s to the end of ``steps`` control steps (10 s by default)."""
    state = initial_state(np.array([[0.0, 0.0, np.pi / 2]]), params)
    errors = []
    for _ in range(steps):
        state = step(state, np.array([action]), params)
        errors.append(formation_error(agent_positions(state))[0])
    return float(np.mean(errors[SETTLE - 1 :]))


def cost_ms(params: FormationParams, B: int = 256, n: int = 5) -> float:
    state = initial_state(np.tile([0.0, 0.0, np.pi / 2], (B, 1)), params)
    a = np.tile([0.4, 0.3], (B, 1))
    state = step(state, a, params)
    t0 = time.perf_counter()
    for _ in range(n):
        state = step(state, a, params)
    return (time.perf_counter() - t0) / n * 1e3


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    ap.add_argument(
        "--steps",
        type=int,
        default=100,
        help=f"control steps of each floor run (>= {SETTLE + 1}; default 100: 10 s)",
    )
    ap.add_argument(
        "--batch", type=int, default=256, help="teams B of the cost per control step (default 256)"
    )
    ap.add_argument("--repeats", type=int, default=5, help="timed control steps of the cost (default 5)")
    args = ap.parse_args(argv)
    if args.steps <= SETTLE or args.batch < 1 or args.repeats < 1:
        ap.error(
            f"--steps must be > {SETTLE}, --batch and --repeats >= 1; got {args.steps}, {args.batch}, {args.repeats}"
        )
    B = args.batch
    rows = [
        ("sign(), 1 ms", FormationParams()),
        ("sign(), 0.5 ms", FormationParams(inner_dt=5e-4)),
        ("sign(), 0.1 ms", FormationParams(inner_dt=1e-4)),
        ("boundary layer eps 0.1, 1 ms", FormationParams(sign_epsilon=0.1)),
    ]
    print(
        f"| follower law | floor, leaders still [m] | floor, leaders moving [m] | ms per control step (B={B}) |"
    )
    print("|---|---|---|---|")
    res = {}
    for name, p in rows:
        res[name] = (
            floor(p, (0.0, 0.0), args.steps),
            floor(p, (0.4, 0.3), args.steps),
            cost_ms(p, B, args.repeats),
        )
        print(f"| {name} | {res[name][0]:.4f} | {res[name][1]:.4f} | {res[name][2]:.1f} |")
    s, b = res["sign(), 1 ms"], res["boundary layer eps 0.1, 1 ms"]
    print(
        f"floor ratio sign() / boundary layer at 1 ms: {s[0] / b[0]:.1f}x (still), {s[1] / b[1]:.1f}x (moving); "
        f"cost ratio {b[2] / s[2]:.2f}x"
    )


if __name__ == "__main__":
    main()
