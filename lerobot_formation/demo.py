"""The README's main job: evaluates the pretrained default against MPPI and PAC on the dataset
protocol (100 scenes of its training dataset, shipped with the model) and on 100 unseen scenes,
then writes the paper's tables and figures to outputs/demo. Extra arguments are passed on to
``lerobot-formation-bench``."""

from __future__ import annotations

import sys
from pathlib import Path

from lerobot_formation.bench import main as bench_main

PRETRAINED = Path(__file__).resolve().parent.parent / "pretrained" / "formation_diffusion_cpu"


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if PRETRAINED.is_dir():
        defaults = [
            "--controllers", "pac,mppi,diffusion,diffusion-adaptive",
            "--policy.path", str(PRETRAINED),
            "--scenes", "dataset:100",
            "--unseen", "random:100",
            "--out", "outputs/demo",
        ]  # fmt: skip
    else:
        defaults = ["--controllers", "pac,mppi", "--scenes", "random:100", "--out", "outputs/demo"]
    return bench_main(defaults + argv)


if __name__ == "__main__":
    raise SystemExit(main())
