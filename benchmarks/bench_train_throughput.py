"""Training throughput with LeRobot's own data loader against the model's pure compute (issue 4).

Everything is built the way ``lerobot-train`` builds it, from the same ``TrainPipelineConfig``
(``TrainPipelineConfig.from_pretrained(--config, cli_args)`` then ``validate()``):
``make_dataset`` (``LeRobotDataset`` with the policy's ``delta_timestamps``), ``make_policy``,
``make_pre_post_processors``, ``make_optimizer_and_scheduler``, an ``EpisodeAwareSampler`` (shuffled,
``drop_n_last_frames``) and a ``torch.utils.data.DataLoader`` with lerobot-train's worker options
(``num_workers``, ``prefetch_factor``, ``persistent_workers``, ``dataloader_multiprocessing_context``),
prepared by an ``Accelerator`` on CPU; each step is lerobot-train's ``update_policy`` (forward,
backward, clipping, optimizer, scheduler, EMA ``update()``).

One run, two phases on the same batches:

1. **with the loader**: ``--steps`` timed steps after ``--warmup`` untimed ones (the first batch pays
   the workers' start-up). Each step's time is split into waiting for the batch (``next()`` on the
   loader), the preprocessor (normalisation) and ``update_policy``. The raw batches are kept.
2. **pure compute**: the loader is shut down, and the kept batches (in memory) go through the same
   preprocessor and ``update_policy`` again.

The waiting share is waiting / (waiting + preprocessor + update) in phase 1. (lerobot-train's own
``data_s`` also counts the preprocessor; it is printed too.)

``--sweep`` first tries LeRobot's public loader options (``--sweep-workers`` x ``--sweep-prefetch``)
and reports the fastest. ``persistent_workers`` only acts at an epoch boundary (non-persistent
workers are re-spawned at each epoch); its cost is reported from the measured worker start-up and
the steps per epoch instead of being run. ``--probe`` measures the per-sample read cost of
``LeRobotDataset.__getitem__`` in this process, with and without the windows, and the share of it
spent copying HF ``datasets`` ``Features``.

Run (full size)::

    HF_HUB_OFFLINE=1 OMP_NUM_THREADS=1 python benchmarks/bench_train_throughput.py \\
        --dataset.root data/formation_pac --config configs/formation_diffusion_cpu.json \\
        --batch-size 256 --steps 20 --num-workers 1 --sweep --probe

Extra ``--key=value`` arguments are passed to the config like lerobot-train's CLI (e.g.
``--policy.horizon=16 --policy.n_action_steps=8 --policy.drop_n_last_frames=7``). The last line is
the ratio of pure-compute throughput to with-loader throughput.
"""

from __future__ import annotations

import argparse
import gc
import logging
import os
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")

import torch  # noqa: E402

import lerobot_formation.plugin  # noqa: E402,F401  (registers the policy, its processor step, the env)


@dataclass
class Phase:
    wait: list[float]
    pre: list[float]
    update: list[float]
    startup: float = 0.0

    @property
    def step_s(self) -> float:
        return sum(self.wait) + sum(self.pre) + sum(self.update)

    def samples_per_s(self, batch_size: int) -> float:
        return batch_size * len(self.update) / self.step_s

    @property
    def wait_share(self) -> float:
        return sum(self.wait) / self.step_s

    @property
    def data_s_share(self) -> float:  # lerobot-train's data_s: next() + preprocessor
        return (sum(self.wait) + sum(self.pre)) / self.step_s


class Trainer:
    """lerobot-train's objects for one config: dataset, policy, processors, optimizer, accelerator."""

    def __init__(self, config: str, cli_args: list[str]):
        from accelerate import Accelerator
        from accelerate.utils import DistributedDataParallelKwargs
        from lerobot.configs.train import TrainPipelineConfig
        from lerobot.datasets.factory import make_dataset
        from lerobot.optim.factory import make_optimizer_and_scheduler
        from lerobot.policies import make_policy, make_pre_post_processors
        from lerobot.utils.logging_utils import AverageMeter, MetricsTracker
        from lerobot.utils.random_utils import set_seed

        cfg = TrainPipelineConfig.from_pretrained(config, cli_args=cli_args)
        cfg.validate()
        if cfg.seed is not None:
            set_seed(cfg.seed)
        self.cfg = cfg
        self.accelerator = Accelerator(
            step_scheduler_with_optimizer=False,
            kwargs_handlers=[DistributedDataParallelKwargs(find_unused_parameters=True)],
            cpu=cfg.policy.device == "cpu",
        )
        self.dataset = make_dataset(cfg)
        policy = make_policy(cfg=cfg.policy, ds_meta=self.dataset.meta)
        self.preprocessor, _ = make_pre_post_processors(
            policy_cfg=cfg.policy, dataset_stats=self.dataset.meta.stats
        )
        optimizer, lr_scheduler = make_optimizer_and_scheduler(cfg, policy)
        self.policy, self.optimizer, self.lr_scheduler = self.accelerator.prepare(
            policy, optimizer, lr_scheduler
        )
        self.policy.train()
        meters = {
            "loss": AverageMeter("loss", ":.3f"),
            "grad_norm": AverageMeter("grdn", ":.3f"),
            "lr": AverageMeter("lr", ":0.1e"),
            "update_s": AverageMeter("updt_s", ":.3f"),
            "dataloading_s": AverageMeter("data_s", ":.3f"),
        }
        self.tracker = MetricsTracker(
            cfg.batch_size, self.dataset.num_frames, self.dataset.num_episodes, meters, initial_step=0
        )

    def dataloader(self, num_workers: int, prefetch_factor: int, persistent_workers: bool):
        """The DataLoader exactly as lerobot-train builds it, for these worker options."""
        from lerobot.datasets import EpisodeAwareSampler

        from lerobot_formation.compat.lerobot_compat import train_dataloader_worker_kwargs

        cfg, ds = self.cfg, self.dataset
        cfg.num_workers, cfg.prefetch_factor, cfg.persistent_workers = (
            num_workers,
            prefetch_factor,
            persistent_workers,
        )
        sampler = EpisodeAwareSampler(
            ds.meta.episodes["dataset_from_index"],
            ds.meta.episodes["dataset_to_index"],
            episode_indices_to_use=ds.episodes,
            drop_n_last_frames=getattr(cfg.policy, "drop_n_last_frames", 0),
            shuffle=True,
            seed=cfg.seed if cfg.seed is not None else 0,
            absolute_to_relative_idx=ds.absolute_to_relative_idx,
        )
        loader = torch.utils.data.DataLoader(
            ds,
            num_workers=cfg.num_workers,
            batch_size=cfg.batch_size,
            shuffle=False,
            sampler=sampler,
            pin_memory=False,
            drop_last=False,
            **train_dataloader_worker_kwargs(cfg),
        )
        return self.accelerator.prepare(loader), len(sampler)

    def step(self, raw: dict) -> tuple[float, float]:
        """Preprocessor + lerobot-train's update_policy on one raw batch: (pre_s, update_s)."""
        from lerobot.scripts.lerobot_train import update_policy

        t0 = time.perf_counter()
        batch = self.preprocessor(dict(raw))
        t1 = time.perf_counter()
        update_policy(
            self.tracker,
            self.policy,
            batch,
            self.optimizer,
            self.cfg.optimizer.grad_clip_norm,
            accelerator=self.accelerator,
            lr_scheduler=self.lr_scheduler,
        )
        return t1 - t0, time.perf_counter() - t1


def _keep(batch: dict) -> dict:
    return {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in batch.items()}


def run_loader(
    tr: Trainer, workers: int, prefetch: int, persistent: bool, steps: int, warmup: int, keep: bool
) -> tuple[Phase, list[dict], int]:
    """Phase 1: steps through lerobot-train's loader. Returns the timings, the raw batches (if keep)
    and the sampler's length (frames per epoch)."""
    from lerobot.utils.utils import cycle

    t0 = time.perf_counter()
    loader, epoch_frames = tr.dataloader(workers, prefetch, persistent)
    it = cycle(loader)
    phase, kept = Phase([], [], []), []
    for i in range(warmup + steps):
        t = time.perf_counter()
        raw = next(it)
        wait = time.perf_counter() - t
        if i == 0:
            phase.startup = time.perf_counter() - t0
        if keep and i >= warmup:
            kept.append(_keep(raw))
        pre, upd = tr.step(raw)
        if i >= warmup:
            phase.wait.append(wait)
            phase.pre.append(pre)
            phase.update.append(upd)
    # Shut the workers down before anything else is timed (persistent workers outlive the iterator).
    workers_iter = getattr(loader, "_iterator", None)
    if workers_iter is not None and hasattr(workers_iter, "_shutdown_workers"):
        workers_iter._shutdown_workers()
    del it, loader
    gc.collect()
    return phase, kept, epoch_frames


def run_compute(tr: Trainer, batches: list[dict]) -> Phase:
    """Phase 2: the same batches, from memory."""
    tr.step(batches[0])  # warm-up
    phase = Phase([], [], [])
    for raw in batches:
        pre, upd = tr.step(raw)
        phase.wait.append(0.0)
        phase.pre.append(pre)
        phase.update.append(upd)
    return phase


def probe_reads(tr: Trainer, n: int) -> None:
    """Per-sample cost of LeRobotDataset.__getitem__ here, windowed and not; share in Features.copy."""
    import cProfile
    import pstats

    import numpy as np
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = tr.dataset
    rng = np.random.default_rng(0)
    idx = [int(i) for i in rng.integers(0, len(ds), n)]

    def ms_per_sample(d) -> float:
        d[idx[0]]
        t = time.perf_counter()
        for i in idx:
            d[i]
        return (time.perf_counter() - t) / n * 1e3

    windowed = ms_per_sample(ds)
    plain = LeRobotDataset(ds.repo_id, root=ds.root, episodes=ds.episodes)
    unwindowed = ms_per_sample(plain)
    prof = cProfile.Profile()
    prof.enable()
    for i in idx[: max(20, n // 4)]:
        ds[i]
    prof.disable()
    st = pstats.Stats(prof)
    total = st.total_tt
    copy = sum(v[3] for k, v in st.stats.items() if k[2] == "copy" and k[0].endswith("features.py"))
    keys = {k: len(v) for k, v in (ds.reader.delta_indices or {}).items()}
    # LeRobot's other public reader, --dataset.streaming=true (an IterableDataset: no
    # EpisodeAwareSampler, shuffling within a 1000-frame buffer, one worker per parquet file).
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.streaming_dataset import StreamingLeRobotDataset

    streaming = StreamingLeRobotDataset(
        ds.repo_id, root=ds.root, delta_timestamps=resolve_delta_timestamps(tr.cfg.policy, ds.meta)
    )
    if ds.num_frames >= 3 * streaming.buffer_size:  # steady state: one new frame read per sample
        stream_it = iter(streaming)
        next(stream_it)  # fills the shuffle buffer
        t = time.perf_counter()
        for _ in range(n):
            next(stream_it)
        stream = f"{(time.perf_counter() - t) / n * 1e3:.2f} ms per sample"
    else:
        stream = "not measured (the dataset is smaller than its shuffle buffer)"
    print(
        f"per-sample read, this process: {windowed:.2f} ms windowed ({len(keys)} keys, rows {keys}), "
        f"{unwindowed:.2f} ms without windows ({windowed / unwindowed:.0f}x); "
        f"{len(ds.hf_dataset.column_names)} columns per query; "
        f"{100 * copy / total:.0f} % of the windowed read time is datasets' Features.copy (cProfile); "
        f"--dataset.streaming=true reader: {stream} (sequential reads, {streaming.buffer_size}-frame shuffle buffer)",
        flush=True,
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset.root", dest="dataset_root", required=True)
    ap.add_argument("--dataset.repo_id", dest="repo_id", default=None, help="default: the config's")
    ap.add_argument("--config", default="configs/formation_diffusion_cpu.json")
    ap.add_argument("--batch-size", type=int, default=256)
    ap.add_argument("--steps", type=int, default=20, help="timed steps per phase")
    ap.add_argument("--warmup", type=int, default=2, help="untimed steps before timing (worker start-up)")
    ap.add_argument("--num-workers", type=int, default=None, help="default: the config's num_workers")
    ap.add_argument("--prefetch-factor", type=int, default=None, help="default: the config's")
    ap.add_argument(
        "--persistent-workers", choices=("true", "false"), default=None, help="default: the config's"
    )
    ap.add_argument("--sweep", action="store_true", help="try the loader options first")
    ap.add_argument("--sweep-workers", default="0,1,2,3")
    ap.add_argument("--sweep-prefetch", default="2,4,8")
    ap.add_argument("--sweep-steps", type=int, default=None, help="timed steps per sweep setting")
    ap.add_argument("--probe", action="store_true", help="measure the per-sample read cost")
    ap.add_argument(
        "--fast-reads", action="store_true", help="also measure lerobot_formation.compat.fast_reads"
    )
    ap.add_argument("--probe-samples", type=int, default=200)
    args, overrides = ap.parse_known_args(argv)
    for o in overrides:
        if not o.startswith("--"):
            ap.error(f"unrecognised argument {o!r} (config overrides look like --policy.horizon=16)")

    logging.getLogger().setLevel(logging.WARNING)
    from lerobot_formation.compat import fast_reads

    fast_reads.uninstall()  # the stock reader first, whatever imported the plugin
    # Spawned workers re-import this script (and with it the plugin): keep them stock too.
    os.environ["LEROBOT_FORMATION_FAST_READS"] = "0"
    cli = [
        f"--dataset.root={args.dataset_root}",
        f"--batch_size={args.batch_size}",
        "--env_eval_freq=0",
        "--wandb.enable=false",
        f"--output_dir={Path(tempfile.gettempdir()) / f'bench_train_throughput_{os.getpid()}'}",
        *([f"--dataset.repo_id={args.repo_id}"] if args.repo_id else []),
        *overrides,
    ]
    t0 = time.perf_counter()
    tr = Trainer(args.config, cli)
    cfg = tr.cfg
    workers = cfg.num_workers if args.num_workers is None else args.num_workers
    prefetch = cfg.prefetch_factor if args.prefetch_factor is None else args.prefetch_factor
    persistent = (
        cfg.persistent_workers if args.persistent_workers is None else args.persistent_workers == "true"
    )
    B = cfg.batch_size
    n_params = sum(p.numel() for p in tr.policy.parameters() if p.requires_grad)
    print(
        f"config {args.config}: policy {cfg.policy.type}, horizon {cfg.policy.horizon}, down_dims "
        f"{list(cfg.policy.down_dims)}, {n_params / 1e6:.2f} M trainable parameters; dataset "
        f"{tr.dataset.num_episodes} episodes, {tr.dataset.num_frames} frames, windows "
        f"{ {k: len(v) for k, v in (tr.dataset.reader.delta_indices or {}).items()} }; batch {B}; "
        f"torch threads {torch.get_num_threads()}, {os.cpu_count()} CPUs; set-up {time.perf_counter() - t0:.1f} s",
        flush=True,
    )
    if args.probe:
        probe_reads(tr, args.probe_samples)

    if args.sweep:
        sweep_steps = args.sweep_steps or args.steps
        rows = []
        settings = []
        for w in (int(x) for x in args.sweep_workers.split(",")):
            for pf in (int(x) for x in args.sweep_prefetch.split(",")) if w > 0 else [None]:
                settings.append((w, pf))
        print(f"sweep: {len(settings)} settings x {sweep_steps} steps (+{args.warmup} warm-up)", flush=True)
        for w, pf in settings:
            ph, _, epoch_frames = run_loader(tr, w, pf or 2, True, sweep_steps, args.warmup, keep=False)
            rows.append((w, pf, ph))
            print(
                f"  num_workers={w} prefetch_factor={pf if pf else '-'}: {ph.samples_per_s(B):6.1f} samples/s, "
                f"waiting {100 * ph.wait_share:4.1f} % of step time, update {statistics.mean(ph.update):.3f} s/step, "
                f"first batch after {ph.startup:.1f} s",
                flush=True,
            )
        w, pf, best = max(rows, key=lambda r: r[2].samples_per_s(B))
        print(
            f"best loader setting: --num_workers={w}"
            + (f" --prefetch_factor={pf}" if pf else "")
            + f" ({best.samples_per_s(B):.1f} samples/s, waiting {100 * best.wait_share:.1f} % of step time)",
            flush=True,
        )
        spawned = [ph.startup for ww, _, ph in rows if ww > 0]
        if spawned:
            steps_per_epoch = max(1, epoch_frames // B)
            epoch_s = steps_per_epoch * B / best.samples_per_s(B)
            print(
                f"persistent_workers only acts at an epoch end: an epoch is {steps_per_epoch} steps of {B} "
                f"(~{epoch_s:.0f} s here); re-spawning workers ({cfg.dataloader_multiprocessing_context}, "
                f"first batch after up to {max(spawned):.1f} s) would add {100 * max(spawned) / epoch_s:.2f} % "
                "per epoch with --persistent_workers=false",
                flush=True,
            )

    print(
        f"main run: num_workers={workers} prefetch_factor={prefetch if workers else '-'} "
        f"persistent_workers={persistent if workers else '-'} context="
        f"{cfg.dataloader_multiprocessing_context if workers else '-'}; {args.steps} steps (+{args.warmup} warm-up)",
        flush=True,
    )
    loaded, kept, _ = run_loader(tr, workers, prefetch, persistent, args.steps, args.warmup, keep=True)
    compute = run_compute(tr, kept)
    with_loader = loaded.samples_per_s(B)
    pure = compute.samples_per_s(B)
    per_sample_wait = sum(loaded.wait) / (len(loaded.wait) * B) * 1e3
    print(
        f"step time with the loader: {loaded.step_s / len(loaded.update):.3f} s = waiting "
        f"{statistics.mean(loaded.wait):.3f} + preprocessor {statistics.mean(loaded.pre):.3f} + update "
        f"{statistics.mean(loaded.update):.3f}; pure compute {compute.step_s / len(compute.update):.3f} s "
        f"(update {statistics.mean(compute.update):.3f}); first batch after {loaded.startup:.1f} s"
    )
    print(f"with LeRobot's data loader: {with_loader:.1f} samples/s")
    print(f"pure compute (same batches, in memory): {pure:.1f} samples/s")
    print(
        f"waiting for data: {100 * loaded.wait_share:.1f} % of step time at batch {B} "
        f"({per_sample_wait:.2f} ms per sample not hidden by the workers; lerobot-train's data_s share, "
        f"which also counts the preprocessor: {100 * loaded.data_s_share:.1f} %)"
    )
    print(f"ratio pure compute / with loader: {pure / with_loader:.2f}x")
    if args.fast_reads:
        # The plugin's fix: LeRobot's reader with lerobot_formation.compat.fast_reads (in-memory columns),
        # same batches, same update; in the main process (--num_workers=0) and, if the stock run used
        # workers, with the same workers (a pickled reader installs the fast path in each worker).
        from lerobot_formation.compat import fast_reads

        os.environ["LEROBOT_FORMATION_FAST_READS"] = "1"
        fast_reads.install()
        results = {}
        for n in sorted({0, workers}):
            fast, _, _ = run_loader(
                tr, n, prefetch if n else 2, persistent and n > 0, args.steps, args.warmup, keep=False
            )
            results[n] = fast
            print(
                f"with fast_reads (num_workers={n}): {fast.samples_per_s(B):.1f} samples/s, waiting "
                f"{100 * fast.wait_share:.1f} % of step time (lerobot-train's data_s share "
                f"{100 * fast.data_s_share:.1f} %)"
            )
        best_n = min(results, key=lambda n: results[n].wait_share)
        best = results[best_n]
        print(
            f"waiting share: stock {100 * loaded.wait_share:.1f} % -> fast_reads {100 * best.wait_share:.1f} % "
            f"(num_workers={best_n}); throughput fast_reads / stock loader: {best.samples_per_s(B) / with_loader:.2f}x"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
