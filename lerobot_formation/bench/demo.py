"""The README's main job: evaluates the pretrained default (standard sampling and its best-of-10
safety layer) against MPPI and PAC on 50 unseen scenes of the paper's layout, and the diffusion
controllers on 20 unseen hard scenes (gates, blockers, dense, other goals), then writes the tables
and figures to outputs/demo. Extra arguments are passed on to ``lerobot-formation-bench`` (later
ones win: ``--scenes random:100 --unseen hard:100`` is the full protocol)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from lerobot_formation.bench.cli import build_parser
from lerobot_formation.bench.cli import main as bench_main
from lerobot_formation.core.scene import UNSEEN_SEED_START

# the repository root's pretrained/ (this file is lerobot_formation/bench/demo.py)
PRETRAINED = Path(__file__).resolve().parents[2] / "pretrained" / "formation_diffusion_route_v1"


def default_arguments() -> list[str]:
    """The bench arguments of the demo: the default against PAC and MPPI; only PAC and MPPI when the
    checkpoint folder is missing (an installed package without the repository)."""
    if (PRETRAINED / "config.json").is_file():
        return [
            "--controllers", "pac,mppi,diffusion,diffusion-bestof",
            "--policy.path", str(PRETRAINED),
            "--scenes", "random:50",
            "--unseen", "hard:20",
            "--out", "outputs/demo",
        ]  # fmt: skip
    print(f"demo: no pretrained default at {PRETRAINED}; running PAC and MPPI only")
    return ["--controllers", "pac,mppi", "--scenes", "random:100", "--out", "outputs/demo"]


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    defaults = default_arguments()
    args = build_parser().parse_args(defaults + argv)
    if args.unseen:  # say what the two sets are: both unseen, the second the hard suite
        print(
            f"demo: {args.controllers} on {args.scenes}, then the diffusion controllers on {args.unseen}; "
            f"scene seeds from {UNSEEN_SEED_START if args.seed is None else args.seed} on, which no "
            "training dataset uses (both sets are unseen)"
        )
    start = time.time()
    # the demo's folder is its own: a new demo replaces the last one (unless --resume is asked for)
    replace = [] if {"--resume", "--overwrite"} & set(argv) else ["--overwrite"]
    code = bench_main(defaults + replace + argv)
    if code == 0:  # the last line names what to open (the bench listed the figures once, above)
        out = Path(args.out)
        pngs = [p for p in out.glob("*.png") if p.stat().st_mtime >= start - 1] if not args.no_figures else []
        figures = f" and the {len(pngs)} figures listed above" if pngs else ""
        print(f"demo: done in {time.time() - start:.1f} s; open {out / 'tables.md'}{figures}")
    return code


if __name__ == "__main__":
    raise SystemExit(main())
