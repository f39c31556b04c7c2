"""Formation-error floor of the follower law: the paper's sign() against the boundary-layer variant,
and the cost of one 0.1 s control step (B = 256 teams) for each inner step.

From the paper's start with the leaders still, and with the leaders driving a curve
(v = 0.4 m/s, omega = 0.3 rad/s), the floor is the mean formation error e_d from t = 2 s to 10 s.
Run: ``python benchmarks/bench_follower_floor.py``. The last line is the figure: the floor ratio
sign() / boundary layer at 1 ms, at the same cost per step.
"""

from __future__ import annotations

import time

import numpy as np

from lerobot_formation.core.dynamics import (
    FormationParams,
    agent_positions,
    formation_error,
    initial_state,
    step,
)


def floor(params: FormationParams, action) -> float:
    state = initial_state(np.array([[0.0, 0.0, np.pi / 2]]), params)
    errors = []
    for _ in range(100):
        state = step(state, np.array([action]), params)
        errors.append(formation_error(agent_positions(state))[0])
    return float(np.mean(errors[19:]))


def cost_ms(params: FormationParams, B: int = 256, n: int = 5) -> float:
    state = initial_state(np.tile([0.0, 0.0, np.pi / 2], (B, 1)), params)
    a = np.tile([0.4, 0.3], (B, 1))
    state = step(state, a, params)
    t0 = time.perf_counter()
    for _ in range(n):
        state = step(state, a, params)
    return (time.perf_counter() - t0) / n * 1e3


def main() -> None:
    rows = [
        ("sign(), 1 ms", FormationParams()),
        ("sign(), 0.5 ms", FormationParams(inner_dt=5e-4)),
        ("sign(), 0.1 ms", FormationParams(inner_dt=1e-4)),
        ("boundary layer eps 0.1, 1 ms", FormationParams(sign_epsilon=0.1)),
    ]
    print(
        "| follower law | floor, leaders still [m] | floor, leaders moving [m] | ms per control step (B=256) |"
    )
    print("|---|---|---|---|")
    res = {}
    for name, p in rows:
        res[name] = (floor(p, (0.0, 0.0)), floor(p, (0.4, 0.3)), cost_ms(p))
        print(f"| {name} | {res[name][0]:.4f} | {res[name][1]:.4f} | {res[name][2]:.1f} |")
    s, b = res["sign(), 1 ms"], res["boundary layer eps 0.1, 1 ms"]
    print(
        f"floor ratio sign() / boundary layer at 1 ms: {s[0] / b[0]:.1f}x (still), {s[1] / b[1]:.1f}x (moving); "
        f"cost ratio {b[2] / s[2]:.2f}x"
    )


if __name__ == "__main__":
    main()
