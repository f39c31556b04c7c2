"""MPPI tuning sweep: num_samples, horizon, lambda and sigma, one at a time around a centre setting.

Stage 1 (screening) runs every setting on the first ``--scenes`` unseen scenes (seeds from
``--seed-start``, default 1_000_000: disjoint from the dataset's seeds 0..). Stage 2 (confirmation)
runs the best screened setting on ``--confirm`` scenes (default 100) and measures the controller's
cost per episode-step at B = 100. Prints markdown tables and writes JSON.

    python benchmarks/mppi_sweep.py --scenes 40 --confirm 100 --out outputs/mppi_sweep.json

Ranking: success, then fewer collisions, then fewer steps to the goal, then lower cost per step.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from lerobot_formation.core.controllers.mppi import MPPIConfig, MPPIController
from lerobot_formation.core.episodes.metrics import wilson_interval
from lerobot_formation.core.episodes.rollout import COLLISION, SUCCESS, TIMEOUT, rollout
from lerobot_formation.core.perception.conditions import Perception
from lerobot_formation.core.world.dynamics import initial_state
from lerobot_formation.core.world.sampling import UNSEEN_SEED_START, sample_scenes

# The sweep's centre: the pre-sweep defaults. Fixed here (not read from MPPIConfig) so that the
# table does not change when the defaults are set to the winner. Unswept fields use MPPIConfig's defaults.
CENTRE: dict = {"num_samples": 256, "horizon": 30, "lambda_": 1.0, "sigma_v": 0.2, "sigma_omega": 0.8}
# Setting name -> overrides of the centre. One factor at a time.
SETTINGS: dict[str, dict] = {
    "centre": {},
    "K=64": {"num_samples": 64},
    "K=1024": {"num_samples": 1024},
    "T=15": {"horizon": 15},
    "T=45": {"horizon": 45},
    "lambda=0.03": {"lambda_": 0.03},
    "lambda=0.1": {"lambda_": 0.1},
    "lambda=0.3": {"lambda_": 0.3},
    "lambda=10": {"lambda_": 10.0},
    "sigma/2": {"sigma_v": 0.1, "sigma_omega": 0.4},
    "sigma*1.5": {"sigma_v": 0.3, "sigma_omega": 1.2},
}


class _TimedController:
    """Wraps a controller and accumulates the wall time of act() per episode-step."""

    def __init__(self, inner: MPPIController):
        self.inner, self.name = inner, inner.name
        self.seconds, self.episode_steps = 0.0, 0

    def reset(self, view) -> None:
        self.inner.reset(view)

    def act(self, view, idx):
        t0 = time.perf_counter()
        a = self.inner.act(view, idx)
        self.seconds += time.perf_counter() - t0
        self.episode_steps += len(idx)
        return a


def evaluate(cfg: MPPIConfig, seeds: np.ndarray) -> dict:
    scenes = sample_scenes(seeds)
    ctl = _TimedController(MPPIController(cfg))
    t0 = time.perf_counter()
    rec = rollout(scenes, ctl)
    wall = time.perf_counter() - t0
    n = len(rec)
    succ = rec.outcome == SUCCESS
    k = int(succ.sum())
    min_clear = np.nanmin(rec.agent_clearance, axis=1)
    return {
        "n": n,
        "success": k,
        "collision": int((rec.outcome == COLLISION).sum()),
        "timeout": int((rec.outcome == TIMEOUT).sum()),
        "success_rate": k / n,
        "success_ci95": wilson_interval(k, n),
        "mean_steps_success": float(rec.steps[succ].mean()) if k else None,
        "min_formation_clearance": float(min_clear.min()),
        "mean_min_formation_clearance": float(min_clear.mean()),
        "failed_seeds": [int(s) for s in scenes.seeds[~succ]],
        "ms_per_episode_step": 1e3 * ctl.seconds / max(ctl.episode_steps, 1),
        "wall_seconds": wall,
    }


def time_b100(cfg: MPPIConfig, seeds: np.ndarray, reps: int = 5) -> float:
    """ms per episode-step of act() with all B = 100 episodes live (after one warm-up call)."""
    scenes = sample_scenes(seeds[:100])
    ctl = MPPIController(cfg)
    view = Perception.exact(scenes, initial_state(scenes.start))
    ctl.reset(view)
    idx = np.arange(len(scenes))
    ctl.act(view, idx)
    t0 = time.perf_counter()
    for _ in range(reps):
        ctl.act(view, idx)
    return 1e3 * (time.perf_counter() - t0) / (reps * len(idx))


def rank_key(r: dict) -> tuple:
    return (-r["success"], r["collision"], r["mean_steps_success"] or np.inf, r["ms_per_episode_step"])


def table(rows: list[tuple[str, dict, dict]]) -> str:
    head = (
        "| setting | K | T | lambda | sigma_v | sigma_omega | scenes | success | collision | timeout "
        "| success 95% CI | steps to goal | min clearance [m] | ms/episode-step |"
    )
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for name, cfg, r in rows:
        lo, hi = r["success_ci95"]
        steps = f"{r['mean_steps_success']:.1f}" if r["mean_steps_success"] is not None else "-"
        lines.append(
            f"| {name} | {cfg['num_samples']} | {cfg['horizon']} | {cfg['lambda_']:g} | {cfg['sigma_v']:g} "
            f"| {cfg['sigma_omega']:g} | {r['n']} | {r['success']} ({100 * r['success_rate']:.0f} %) "
            f"| {r['collision']} | {r['timeout']} | [{100 * lo:.0f}, {100 * hi:.0f}] % | {steps} "
            f"| {r['min_formation_clearance']:.3f} | {r['ms_per_episode_step']:.2f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=40, help="screening scenes per setting")
    ap.add_argument("--confirm", type=int, default=100, help="scenes for the best setting (0: skip)")
    ap.add_argument("--seed-start", type=int, default=UNSEEN_SEED_START, help="first scene seed")
    ap.add_argument("--settings", nargs="*", default=list(SETTINGS), help=f"subset of {list(SETTINGS)}")
    ap.add_argument("--out", type=Path, default=None, help="JSON output file")
    args = ap.parse_args(argv)
    unknown = [s for s in args.settings if s not in SETTINGS]
    if unknown:
        ap.error(f"unknown settings {unknown}; choose from {list(SETTINGS)}")
    base = replace(MPPIConfig(), **CENTRE)
    screen_seeds = np.arange(args.seed_start, args.seed_start + args.scenes)
    rows = []
    for name in args.settings:
        cfg = replace(base, **SETTINGS[name])
        print(f"screening {name} on {args.scenes} scenes ...", file=sys.stderr, flush=True)
        rows.append((name, asdict(cfg), evaluate(cfg, screen_seeds)))
    print(f"## Screening: {args.scenes} unseen scenes, seeds {screen_seeds[0]}..{screen_seeds[-1]}\n")
    print(table(rows))
    best_name, best_cfg, _ = min(rows, key=lambda r: rank_key(r[2]))
    out = {
        "command": " ".join(["python", *(sys.argv if argv is None else ["benchmarks/mppi_sweep.py", *argv])]),
        "defaults": asdict(MPPIConfig()),
        "centre": asdict(base),
        "screening": {"seeds": [int(screen_seeds[0]), int(screen_seeds[-1])], "rows": rows},
        "best": best_name,
    }
    if args.confirm:
        seeds = np.arange(args.seed_start, args.seed_start + args.confirm)
        cfg = MPPIConfig(**best_cfg)
        print(f"confirming {best_name} on {args.confirm} scenes ...", file=sys.stderr, flush=True)
        r = evaluate(cfg, seeds)
        r["ms_per_episode_step_b100"] = time_b100(cfg, seeds) if args.confirm >= 100 else None
        print(
            f"\n## Confirmation of `{best_name}`: {args.confirm} unseen scenes, seeds {seeds[0]}..{seeds[-1]}\n"
        )
        print(table([(best_name, best_cfg, r)]))
        if r["ms_per_episode_step_b100"] is not None:
            print(
                f"\nact() cost with B = 100 live episodes: {r['ms_per_episode_step_b100']:.2f} ms per episode-step"
            )
        print(f"failed seeds: {r['failed_seeds']}")
        out["confirmation"] = {"seeds": [int(seeds[0]), int(seeds[-1])], "setting": best_name, "result": r}
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1, default=float))
        print(f"\nwrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
