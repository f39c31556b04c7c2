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

PRETRAINED = Path(__file__).resolve().parent.parent / "pretrained" / "formation_diffusion_safe"


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if PRETRAINED.is_dir():
        defaults = [
            "--controllers", "pac,mppi,diffusion,diffusion-bestof",
            "--policy.path", str(PRETRAINED),
            "--scenes", "random:50",
            "--unseen", "hard:20",
            "--out", "outputs/demo",
        ]  # fmt: skip
    else:
        defaults = ["--controllers", "pac,mppi", "--scenes", "random:100", "--out", "outputs/demo"]
    start = time.time()
    code = bench_main(defaults + argv)
    args = build_parser().parse_args(defaults + argv)
    if code == 0 and not args.no_figures:  # the last line names what to open
        out = Path(args.out)
        pngs = sorted(p.name for p in out.glob("*.png") if p.stat().st_mtime >= start - 1)
        print(f"demo: {len(pngs)} figures in {out}: {', '.join(pngs)}")
    return code


if __name__ == "__main__":
    raise SystemExit(main())
