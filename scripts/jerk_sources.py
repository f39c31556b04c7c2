"""Where a diffusion controller's jerk comes from: the steps next to each kind of replan or filter event.

    python scripts/jerk_sources.py --policy.path pretrained/formation_diffusion_route_v1 --level level3 \
        --scenes 100 [--seed 5000000] [--chunk-smoothing N] [--horizon N] [other safety overrides]

The jerk (``core.episodes.metrics``, SPEC) at step t is the third difference of the midpoint position over
positions t .. t+3, i.e. v_{t+2} - 2 v_{t+1} + v_t of the commands t, t+1 and t+2: a command that
differs from the one before it at step s shows in the jerk at t = s-2 and s-1. Each jerk value of a
successful episode is put in the class of the first event, in this order, at its step t+1 or t+2:

- ``filter``: the CBF filter changed the command;
- ``escape``: a replan kept an escape manoeuvre (nothing sampled was safe);
- ``proposal``: a replan kept route pursuit's proposal (``core.safety.layer.ROUTE_PROPOSAL``);
- ``replan after a cut``: a replan the filter caused (the plan was cut short);
- ``replan``: a scheduled replan that kept one of the model's samples;
- ``none``: none of these (the chunk running on).

One line per class: its share of the steps, its mean jerk and its share of all jerk (pooled over the
successful episodes' steps), then the summary line of ``bench.level_report`` (success, collisions,
timeouts; the mean over episodes of their jerk and smoothness), as ``scripts/collision_report.py``
prints it. The events are recorded by ``bench.level_report.recording_replanner``, a ``Replanner``
subclass that the bench's controller runs instead of its own; nothing else changes. The safety overrides (``--chunk-smoothing``,
``--horizon``, ``--safety-margin``, ...) are ``scripts/collision_report.py``'s
(``bench.level_report.add_arguments``).
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402

from lerobot_formation.threads import add_threads_argument, apply_threads  # noqa: E402

EVENTS = ("filter", "escape", "proposal", "replan_cut", "replan")  # in order of precedence
CLASSES = ("filter", "escape", "proposal", "replan after a cut", "replan", "none")


def jerk_sources(positions: np.ndarray, steps: np.ndarray, events: dict[str, np.ndarray], dt: float):
    """Per class (``CLASSES``): (number of jerk values, their sum) over episodes.

    ``positions`` (B, T + 1, 2) midpoint positions, ``steps`` (B,) each episode's length (only
    positions 0 .. steps are read), ``events`` name -> (B, T) bool per step, for every name of
    ``EVENTS``. The jerk value at step t goes to the first event found at step t+1 or t+2 (module
    docstring), else to "none"."""
    count = dict.fromkeys(CLASSES, 0)
    total = dict.fromkeys(CLASSES, 0.0)
    for b in range(len(positions)):
        n = int(steps[b])
        if n < 3:
            continue
        jerk = np.linalg.norm(np.diff(positions[b, : n + 1], n=3, axis=0), axis=-1) / dt**3  # (n - 2,)
        label = np.full(len(jerk), len(EVENTS))  # index into CLASSES; last: "none"
        for k in reversed(range(len(EVENTS))):  # the first event in EVENTS wins
            flag = events[EVENTS[k]][b]
            near = flag[1 : len(jerk) + 1] | flag[2 : len(jerk) + 2]
            label[near] = k
        for k, name in enumerate(CLASSES):
            count[name] += int(np.sum(label == k))
            total[name] += float(np.sum(jerk[label == k]))
    return count, total


def main(argv: list[str] | None = None) -> int:
    from lerobot_formation.bench import level_report
    from lerobot_formation.core.episodes.rollout import SUCCESS

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    level_report.add_arguments(ap, policy_required=True)
    add_threads_argument(ap, "torch threads")
    args = ap.parse_args(argv)
    apply_threads(args.threads)
    try:
        settings = {k: getattr(args, k) for k in level_report.RUN_FLAGS}
        run = level_report.run_flags("diffusion-safe", level_report.recording_replanner, **settings)
    except ValueError as e:  # a bad level name
        ap.error(str(e))
    rec = run.records
    ok = rec.outcome == SUCCESS
    events = {name: flags[ok] for name, flags in run.controller.replanner.events.items()}
    count, total = jerk_sources(rec.poses[ok, :, :2], rec.steps[ok], events, run.params.dt)
    steps, jerk = sum(count.values()), sum(total.values())
    for name in CLASSES:
        mean = total[name] / count[name] if count[name] else float("nan")
        print(
            f"{name:<19} {100 * count[name] / max(steps, 1):5.1f} % of the steps, mean jerk {mean:6.3f}, "
            f"{100 * total[name] / max(jerk, 1e-12):5.1f} % of the jerk"
        )
    print(run.summary())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
