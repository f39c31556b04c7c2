"""Dataset generation: the full PAC dataset (default 1878 episodes), and the episode-buffer writer
against LeRobot's plain per-frame ``add_frame`` loop on the same episodes.

Run: ``python benchmarks/bench_dataset.py [--episodes 1878] [--write-episodes 200]``
(``--episodes 2 --write-episodes 2`` is a smoke run).
The last line is the figure: the whole dataset's time, and the writer speed-up ratio.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

from datasets_scripts.generate_pac_dataset import PAPER_EPISODES  # noqa: E402
from lerobot_formation.compat.lerobot_compat import skip_noop_image_embedding  # noqa: E402
from lerobot_formation.core.world.dynamics import FormationParams  # noqa: E402
from lerobot_formation.data import (
    dataset_frames,
    lerobot_writer,
    pac_episodes,  # noqa: E402
)


def write_only(episodes, root: Path, fast: bool) -> float:
    """Seconds to write pre-simulated episodes through LeRobot's writer."""
    import contextlib

    import datasets as hf_datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    hf_datasets.disable_progress_bars()
    t0 = time.perf_counter()
    ds = LeRobotDataset.create(
        "local/bench", dataset_frames.FPS, dataset_frames.dataset_features(), root=root, use_videos=False
    )
    ctx = skip_noop_image_embedding(ds.meta.features) if fast else contextlib.nullcontext()
    with ctx:
        for frames in episodes:
            lerobot_writer.write_episode(ds, frames, fast=fast)
        ds.finalize()
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    ap.add_argument("--episodes", type=int, default=PAPER_EPISODES)
    ap.add_argument("--write-episodes", type=int, default=200, help="episodes for the writer comparison")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="bench_dataset_"))
    try:
        # 1. The whole dataset, as the CLI makes it.
        s = lerobot_writer.generate(tmp / "full", "local/bench_full", args.episodes, progress=False)
        print(
            f"full dataset: {s['episodes']} episodes, {s['frames']} frames, {s['mb']:.1f} MB in {s['seconds']:.1f} s "
            f"({s['episodes'] / s['seconds']:.1f} episodes/s, {s['frames'] / s['seconds']:,.0f} frames/s); "
            f"PAC success while generating {s['pac_success_rate']:.1%}"
        )
        # 2. Writer only, same episodes both ways.
        g = pac_episodes.Generator(FormationParams(), batch_size=args.write_episodes + 10)
        eps = list(g.episodes(pac_episodes.seed_stream(0, 1, 0), args.write_episodes))
        frames = sum(len(e["action"]) for e in eps)
        fast = write_only(eps, tmp / "fast", fast=True)
        slow = write_only(eps, tmp / "slow", fast=False)
        print(f"writer, {len(eps)} episodes / {frames} frames: episode buffers {frames / fast:,.0f} frames/s")
        print(
            f"writer, {len(eps)} episodes / {frames} frames: per-frame add_frame {frames / slow:,.0f} frames/s"
        )
        print(
            f"whole dataset {s['seconds']:.1f} s ({s['episodes']} episodes); "
            f"writer speed-up vs add_frame: {slow / fast:.1f}x"
        )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
