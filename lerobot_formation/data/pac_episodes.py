"""PAC episodes for the dataset: scenes by seed, simulated batch by batch on the NumPy core
(optionally in worker processes that die with the generating process), successful ones kept in
seed order; and the seeds and episode counts of each shard."""

from __future__ import annotations

import contextlib
import os
import sys
import time

import numpy as np

from lerobot_formation.core.conditions import Conditions
from lerobot_formation.core.dynamics import FormationParams
from lerobot_formation.core.rollout import SUCCESS, PACController, rollout
from lerobot_formation.core.scene import SceneConfig, Scenes, sample_scenes
from lerobot_formation.data.dataset_frames import MAX_OBSTACLES, episode_frames


def simulate_batch(
    seeds: np.ndarray,
    scenes: Scenes | None,
    params: FormationParams,
    obstacle_encoding: str,
    scene_config: SceneConfig | None = None,
    scene_slots: int = MAX_OBSTACLES,
    conditions: Conditions | None = None,
) -> tuple[int, list[dict[str, np.ndarray]]]:
    """PAC on one batch of scenes (the seeds' scenes, or the given ones), under ``conditions`` (then
    the frames hold what the team observed): (attempted, frames of the successful episodes in seed
    order). Runs in a worker process when generation is pipelined."""
    if scenes is None:
        scenes = sample_scenes(seeds, scene_config)
    on = conditions is not None and conditions.enabled
    rec = rollout(
        scenes,
        PACController(params=params),
        params,
        conditions=conditions if on else None,
        record_observations=(obstacle_encoding, None) if on else None,
    )
    ok = np.flatnonzero(rec.outcome == SUCCESS)
    return len(scenes), [episode_frames(rec, scenes, b, obstacle_encoding, scene_slots) for b in ok]


class Generator:
    """Collects successful PAC episodes in seed order, batch by batch.

    With ``workers > 0`` the batches are simulated in worker processes, ``workers`` batches ahead,
    while the caller writes: on 2 cores simulation and LeRobot's writer then overlap. The episodes
    and their order do not depend on ``workers``.
    """

    def __init__(
        self,
        params: FormationParams,
        batch_size: int = 256,
        obstacle_encoding: str = "grid",
        workers=0,
        scene_config: SceneConfig | None = None,
        scene_slots: int = MAX_OBSTACLES,
        conditions: Conditions | None = None,
    ):
        self.conditions = conditions
        self.scene_config = scene_config
        self.scene_slots = scene_slots
        self.params = params
        self.batch_size = batch_size
        self.obstacle_encoding = obstacle_encoding
        self.workers = workers
        self.attempted = 0
        self.succeeded = 0

    @property
    def _sim_args(self) -> tuple:
        return self.params, self.obstacle_encoding, self.scene_config, self.scene_slots, self.conditions

    def _batches(self, seeds_iter, scenes_file: Scenes | None):
        while True:
            seeds = np.asarray([next(seeds_iter) for _ in range(self.batch_size)])
            if scenes_file is not None:
                seeds = seeds[seeds < len(scenes_file)]
                if len(seeds) == 0:
                    return
                yield seeds, scenes_file[seeds]
            else:
                yield seeds, None

    def episodes(self, seeds_iter, n: int, scenes_file: Scenes | None = None, progress=None):
        """Yield the frames of successful episodes until n are produced."""
        produced = 0
        batches = self._batches(seeds_iter, scenes_file)
        if self.workers > 0:
            import concurrent.futures
            import multiprocessing

            pool = concurrent.futures.ProcessPoolExecutor(
                self.workers,
                mp_context=multiprocessing.get_context("fork"),
                initializer=_die_with_parent,
                initargs=(os.getpid(),),
            )
            pending = [
                pool.submit(simulate_batch, *bt, *self._sim_args) for bt in _take(batches, self.workers)
            ]

            def results():
                while pending:
                    out = pending.pop(0).result()
                    for bt in _take(batches, 1):
                        pending.append(pool.submit(simulate_batch, *bt, *self._sim_args))
                    yield out

        else:
            pool = None

            def results():
                for bt in batches:
                    yield simulate_batch(*bt, *self._sim_args)

        try:
            for attempted, frames_list in results():
                self.attempted += attempted
                self.succeeded += len(frames_list)
                for frames in frames_list:
                    if produced >= n:
                        return
                    produced += 1
                    if progress is not None:
                        progress(1)
                    yield frames
                if produced >= n:
                    return
        finally:
            if pool is not None:
                _stop_pool(pool)


def _die_with_parent(parent_pid: int) -> None:
    """Worker initializer: the worker ends when the generating process does, however it ends.

    On Linux ``prctl(PR_SET_PDEATHSIG, SIGKILL)`` has the kernel kill the worker the moment its parent
    dies (SIGKILL included); a daemon thread also polls ``os.getppid()`` every 0.5 s (other systems,
    and the case where the parent died before the prctl call). Without this a killed generation left
    its worker blocked on the result pipe, holding ~500 MB.
    """
    import signal
    import threading

    if sys.platform.startswith("linux"):
        with contextlib.suppress(Exception):
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG = 1
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # the parent's SystemExit handler is not the worker's
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the parent, which stops the workers

    def watch() -> None:
        while True:
            if os.getppid() != parent_pid:
                os._exit(1)
            time.sleep(0.5)

    if os.getppid() != parent_pid:
        os._exit(1)
    threading.Thread(target=watch, name="die-with-parent", daemon=True).start()


def _stop_pool(pool) -> None:
    """Shut the worker pool down without waiting for running batches: cancel the queued ones and
    terminate the workers (on success they are idle; on an error or a signal they may be mid-batch)."""
    procs = list(getattr(pool, "_processes", {}).values())  # CPython's ProcessPoolExecutor
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        with contextlib.suppress(Exception):
            proc.terminate()
    for proc in procs:
        with contextlib.suppress(Exception):
            proc.join(timeout=5)


def _take(it, k: int) -> list:
    out = []
    for _ in range(k):
        try:
            out.append(next(it))
        except StopIteration:
            break
    return out


# -- shards: shard i of n takes seeds start + i, start + i + n, ... (merged with lerobot-edit-dataset)
def seed_stream(start: int, num_shards: int, shard_index: int):
    s = start + shard_index
    while True:
        yield s
        s += num_shards


def shard_episodes(total: int, num_shards: int, shard_index: int) -> int:
    return total // num_shards + (1 if shard_index < total % num_shards else 0)
