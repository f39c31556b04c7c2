"""Success of every checkpoint of a lerobot-train run: how long training takes to reach a target.

    python scripts/checkpoint_curve.py outputs/train_cpu --dataset.root data/formation_pac_list \
        --scenes dataset:100 --target 62

For each ``checkpoints/<step>/pretrained_model`` (oldest first) it runs the standard policy (one
sample per replan, seed 0) on the same scenes with the batched engine and prints the step, the
training wall time at which the checkpoint was written (its model file's modification time minus
``--start`` (the time the run was launched; default: extrapolated back from the first two
checkpoints) and the success with its Wilson 95 % interval.
The last line names the first checkpoint at or above ``--target`` %.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
from pathlib import Path

from lerobot_formation.threads import add_threads_argument, apply_threads

os.environ.setdefault("HF_HUB_OFFLINE", "1")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    ap.add_argument("run", type=Path, help="a lerobot-train output_dir")
    ap.add_argument("--dataset.root", dest="dataset_root", default=None)
    ap.add_argument("--scenes", default="dataset:100")
    ap.add_argument("--seed", type=int, default=1_000_000, help="first seed for random:N")
    ap.add_argument("--target", type=float, default=62.0, help="success %% to reach")
    ap.add_argument(
        "--start", default=None, help="the run's start, HH:MM:SS or ISO time (default: from the checkpoints)"
    )
    ap.add_argument("--out", type=Path, default=None, help="also write the rows as JSON")
    add_threads_argument(ap, "torch threads of the policy")
    args = ap.parse_args(argv)
    apply_threads(args.threads)  # before torch loads

    from lerobot_formation.bench.diffusion_controller import DiffusionController
    from lerobot_formation.bench.evaluation import evaluate
    from lerobot_formation.bench.scene_sets import parse_scenes
    from lerobot_formation.core.episodes.metrics import wilson_interval
    from lerobot_formation.core.episodes.rollout import COLLISION, SUCCESS, TIMEOUT

    ckpts = sorted(p for p in (args.run / "checkpoints").iterdir() if p.name.isdigit())
    if not ckpts:
        raise SystemExit(f"error: {args.run}/checkpoints holds no numbered checkpoints")
    written = [(c / "pretrained_model" / "model.safetensors").stat().st_mtime for c in ckpts]
    if args.start:
        try:  # a time of day is taken on the first checkpoint's date
            day = dt.datetime.fromtimestamp(written[0]).date()
            start = dt.datetime.combine(day, dt.time.fromisoformat(args.start)).timestamp()
        except ValueError:
            try:
                start = dt.datetime.fromisoformat(args.start).timestamp()
            except ValueError:
                raise SystemExit(
                    f"error: --start {args.start!r} is neither HH:MM:SS nor an ISO date-time"
                ) from None
    else:  # assume steady progress up to the first checkpoint
        first_step = int(ckpts[0].name)
        per_step = (written[1] - written[0]) / (int(ckpts[1].name) - first_step) if len(ckpts) > 1 else 0
        start = written[0] - per_step * first_step
    scenes = parse_scenes(args.scenes, args.seed, dataset_root=args.dataset_root)
    rows, reached = [], None
    print(f"{'step':>7} {'wall (min)':>10} {'success %':>10}  95 % interval  collisions timeouts")
    for c, w in zip(ckpts, written, strict=True):
        ctrl = DiffusionController(c / "pretrained_model", seed=0)
        rec = evaluate(ctrl, scenes)
        n_ok = int((rec.outcome == SUCCESS).sum())
        lo, hi = wilson_interval(n_ok, len(rec))
        row = {
            "step": int(c.name),
            "wall_min": (w - start) / 60,
            "success": 100 * n_ok / len(rec),
            "ci95": [100 * lo, 100 * hi],
            "collisions": int((rec.outcome == COLLISION).sum()),
            "timeouts": int((rec.outcome == TIMEOUT).sum()),
        }
        rows.append(row)
        print(
            f"{row['step']:>7} {row['wall_min']:>10.1f} {row['success']:>10.0f}  "
            f"[{row['ci95'][0]:.0f}, {row['ci95'][1]:.0f}]  {row['collisions']:>10} {row['timeouts']:>8}",
            flush=True,
        )
        if reached is None and row["success"] >= args.target:
            reached = row
    if args.out:
        args.out.write_text(json.dumps(rows, indent=2))
    if reached:
        print(
            f"first checkpoint at >= {args.target:g} %: step {reached['step']}, "
            f"{reached['wall_min']:.1f} min of training ({reached['success']:.0f} %)"
        )
    else:
        print(f"no checkpoint reached {args.target:g} % (best {max(r['success'] for r in rows):.0f} %)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
