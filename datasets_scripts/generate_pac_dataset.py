"""PAC demonstrations as a LeRobot dataset (format v3.0), optionally laid out as a hub dataset repo.

Runs the Path-Aware Controller on seeded valid scenes (all episodes of a batch at once, on the NumPy
core), keeps the successful episodes and writes them with LeRobot's own writer
(``LeRobotDataset.create`` -> ``save_episode`` -> ``finalize``).

Usage::

    lerobot-formation-generate --episodes 1878 --root data/formation_pac          # the paper's size
    lerobot-formation-generate --episodes 10 --root /tmp/tiny --push-to /tmp/hub  # + hub-style folder
    # sharded: each shard is a valid dataset; merge them with LeRobot's own tool
    lerobot-formation-generate --num-shards 2 --shard-index 0 --root data/shard0 &
    lerobot-formation-generate --num-shards 2 --shard-index 1 --root data/shard1 &
    wait
    lerobot-edit-dataset --new_repo_id local/formation_pac --new_root data/merged --operation.type merge \
        --operation.repo_ids "['local/shard0', 'local/shard1']" --operation.roots "['data/shard0', 'data/shard1']"

Features (all float32 with names, fps 10, task string ``TASK``):
- ``observation.state`` (7,): midpoint [x, y, cos phi, sin phi, x', y', omega];
- ``observation.environment_state`` (51,) or (66,): obstacle grid, goal (and obstacle list);
- ``action`` (2,): [v, omega] actually applied (clipped);
- ``scene.seed`` (int64), ``scene.obstacles`` (15,), ``scene.goal`` (2,), ``scene.start`` (3,):
  per-frame scene metadata from which evaluation rebuilds the exact scene of every episode. They are
  not ``observation.*`` keys, so policies ignore them, and as ordinary columns they survive LeRobot's
  split and merge.

Reliability: the dataset is written to a temporary sibling folder ``.NAME.tmp-PID`` and renamed into
place at the end, so an interrupted run leaves nothing at the destination. On any exit (an error,
Ctrl-C, SIGTERM or SIGHUP, which raise SystemExit) the temporary folder is removed and the simulation
workers stopped; after a SIGKILL the workers die with their parent (``_die_with_parent``) and the next
run into the same destination removes the folder (``remove_stale_temporaries``). A run refuses to
start while a live process writes the same destination, checks again right before the rename, and
the rename never replaces a folder that appeared meanwhile (``rename_noreplace``) unless
``--overwrite``. The same arguments give byte-identical data files.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from lerobot_formation.core.dynamics import FormationParams
from lerobot_formation.core.observation import STATE_DIM, STATE_NAMES, observe, observed_velocities
from lerobot_formation.core.obstacle_grid import ENCODINGS, get_encoding
from lerobot_formation.core.rollout import SUCCESS, EpisodeRecords, PACController, rollout
from lerobot_formation.core.scene import (
    SCENE_PRESETS,
    SceneConfig,
    Scenes,
    load_scenes,
    sample_scenes,
    scenes_from_frames,  # noqa: F401 (re-export: it lived here)
)
from lerobot_formation.core.scene import scene_preset as scene_preset_config
from lerobot_formation.env import TASK
from lerobot_formation.lerobot_compat import save_episode_buffer, skip_noop_image_embedding
from lerobot_formation.threads import add_threads_argument, apply_threads

FPS = 10
MAX_OBSTACLES = 5
PAPER_EPISODES = 1878


def dataset_features(obstacle_encoding: str = "grid", scene_slots: int = MAX_OBSTACLES) -> dict:
    """LeRobot features of a PAC dataset; ``scene_slots`` obstacle rows in ``scene.obstacles`` (every
    obstacle of every scene, whatever the observation encodes)."""
    grid_names = get_encoding(obstacle_encoding).names(get_encoding(obstacle_encoding).slots(None))
    return {
        "observation.state": {"dtype": "float32", "shape": (STATE_DIM,), "names": STATE_NAMES},
        "observation.environment_state": {
            "dtype": "float32",
            "shape": (len(grid_names),),
            "names": grid_names,
        },
        "action": {"dtype": "float32", "shape": (2,), "names": ["v", "omega"]},
        "scene.seed": {"dtype": "int64", "shape": (1,), "names": None},
        "scene.obstacles": {
            "dtype": "float32",
            "shape": (3 * scene_slots,),
            "names": [f"obstacle_{k}_{c}" for k in range(scene_slots) for c in ("x", "y", "r")],
        },
        "scene.goal": {"dtype": "float32", "shape": (2,), "names": ["x", "y"]},
        "scene.start": {"dtype": "float32", "shape": (3,), "names": ["x", "y", "phi"]},
    }


def episode_frames(
    rec: EpisodeRecords, scenes: Scenes, b: int, obstacle_encoding: str, scene_slots: int = MAX_OBSTACLES
) -> dict[str, np.ndarray]:
    """The frames of episode b as arrays (n, ...): observation before action t, and action t."""
    n = int(rec.steps[b])
    poses = rec.poses[b, :n]
    actions = rec.actions[b, :n]
    one = slice(b, b + 1)  # the episode's scene, observed at each of its n poses
    seen = observe(
        poses,
        observed_velocities(poses, actions),
        scenes.obstacles[one],
        scenes.mask[one],
        scenes.goal[one],
        obstacle_encoding,
    )
    real = scenes.obstacles[b][scenes.mask[b]]
    if len(real) > scene_slots:
        raise ValueError(f"scene {b} has {len(real)} obstacles, more than the dataset's {scene_slots} slots")
    obs_list = np.zeros((scene_slots, 3), np.float32)
    obs_list[: len(real)] = real
    return {
        "observation.state": seen["agent_pos"],
        "observation.environment_state": seen["environment_state"],
        "action": actions.astype(np.float32),
        "scene.seed": np.full((n, 1), scenes.seeds[b], dtype=np.int64),
        "scene.obstacles": np.repeat(obs_list.reshape(1, -1), n, axis=0),
        "scene.goal": np.repeat(scenes.goal[b : b + 1].astype(np.float32), n, axis=0),
        "scene.start": np.repeat(scenes.start[b : b + 1].astype(np.float32), n, axis=0),
    }


def write_episode(ds, frames: dict[str, np.ndarray], fast: bool = True) -> None:
    """Write one episode through LeRobot's writer. ``fast`` hands ``save_episode`` a pre-built episode
    buffer (``lerobot_compat.save_episode_buffer``) instead of a per-frame ``add_frame`` loop; the
    frames are identical either way. On an untested LeRobot version the loop runs."""
    if fast and save_episode_buffer(ds, frames, TASK):
        return
    for t in range(len(frames["action"])):
        ds.add_frame({**{k: v[t] for k, v in frames.items()}, "task": TASK})
    ds.save_episode()


def simulate_batch(
    seeds: np.ndarray,
    scenes: Scenes | None,
    params: FormationParams,
    obstacle_encoding: str,
    scene_config: SceneConfig | None = None,
    scene_slots: int = MAX_OBSTACLES,
) -> tuple[int, list[dict[str, np.ndarray]]]:
    """PAC on one batch of scenes (the seeds' scenes, or the given ones): (attempted, frames of the
    successful episodes in seed order). Runs in a worker process when generation is pipelined."""
    if scenes is None:
        scenes = sample_scenes(seeds, scene_config)
    rec = rollout(scenes, PACController(params=params), params)
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
    ):
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
        return self.params, self.obstacle_encoding, self.scene_config, self.scene_slots

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


def seed_stream(start: int, num_shards: int, shard_index: int):
    s = start + shard_index
    while True:
        yield s
        s += num_shards


def shard_episodes(total: int, num_shards: int, shard_index: int) -> int:
    return total // num_shards + (1 if shard_index < total % num_shards else 0)


# -- temporary folders and the final rename ---------------------------------------------------------
def _tmp_prefix(root: Path) -> str:
    return f".{root.name}.tmp-"


def _old_prefix(root: Path) -> str:
    return f".{root.name}.old-"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def remove_stale_temporaries(root: Path) -> list[Path]:
    """Remove the ``.NAME.tmp-PID`` / ``.NAME.old-PID`` folders beside ``root`` that runs killed with
    SIGKILL (no cleanup possible) left behind: those whose PID is no longer alive. Returns them.

    Raises:
        FileExistsError: a live process (not this one) is writing ``root`` now.
    """
    root = Path(root)
    removed = []
    if not root.parent.is_dir():
        return removed
    for prefix in (_tmp_prefix(root), _old_prefix(root)):
        for path in sorted(root.parent.glob(f"{prefix}*")):
            pid_text = path.name[len(prefix) :]
            if not pid_text.isdigit() or int(pid_text) == os.getpid():
                continue
            if _pid_alive(int(pid_text)):
                if prefix == _tmp_prefix(root):
                    raise FileExistsError(
                        f"another generation (pid {pid_text}) is writing {root} now (its temporary folder {path}); "
                        f"wait for it, or remove {path} if process {pid_text} is not a generation"
                    )
                continue
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed


def rename_noreplace(src: Path, dst: Path) -> None:
    """``os.rename(src, dst)`` that never replaces ``dst`` (a folder that appeared meanwhile, even an
    empty one, which plain ``rename`` replaces): ``renameat2(RENAME_NOREPLACE)`` on Linux, atomic;
    elsewhere a check right before the rename. Raises FileExistsError if ``dst`` exists."""
    if sys.platform.startswith("linux"):
        import ctypes
        import errno

        libc = ctypes.CDLL(None, use_errno=True)
        fn = getattr(libc, "renameat2", None)
        if fn is not None:
            AT_FDCWD, RENAME_NOREPLACE = -100, 1
            if fn(AT_FDCWD, os.fsencode(src), AT_FDCWD, os.fsencode(dst), RENAME_NOREPLACE) == 0:
                return
            err = ctypes.get_errno()
            if err == errno.EEXIST:
                raise FileExistsError(
                    f"destination {dst} appeared while this run was generating (another generation?); "
                    "nothing was replaced: pass --overwrite to replace it"
                )
            if err not in (errno.ENOSYS, errno.EINVAL):  # unsupported here: fall back
                raise OSError(err, os.strerror(err), str(src), None, str(dst))
    if os.path.lexists(dst):
        raise FileExistsError(
            f"destination {dst} appeared while this run was generating; nothing was replaced"
        )
    os.rename(src, dst)


def generate(
    root: Path,
    repo_id: str,
    episodes: int,
    seed: int = 0,
    obstacle_encoding: str = "grid",
    scenes_path: str | None = None,
    num_shards: int = 1,
    shard_index: int = 0,
    overwrite: bool = False,
    fast_write: bool = True,
    batch_size: int = 256,
    progress: bool = True,
    workers: int = 1,
    scene_preset: str = "paper",
    min_scene_slots: int = 0,
) -> dict:
    """Generate the dataset at ``root`` (atomically) and return a summary dict."""
    import datasets as hf_datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    hf_datasets.disable_progress_bars()  # one bar per episode otherwise

    root = Path(root)
    if root.exists() and not overwrite:
        raise FileExistsError(f"destination {root} already exists; pass --overwrite to replace it")
    n = shard_episodes(episodes, num_shards, shard_index)
    root.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(root)  # of killed runs; refuses if a live generation writes root
    tmp = root.parent / f"{_tmp_prefix(root)}{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    params = FormationParams()
    scene_config = scene_preset_config(scene_preset)
    scenes_file = load_scenes(scenes_path) if scenes_path else None
    if scenes_file is not None:
        held = len(range(shard_index, len(scenes_file), num_shards))  # this shard's scenes of the file
        if n > held:
            raise ValueError(
                f"--episodes {episodes} asks for more episodes than scenes file {scenes_path} holds "
                f"({len(scenes_file)} scenes{f', {held} of them in shard {shard_index}' if num_shards > 1 else ''})"
            )
    # scene.obstacles keeps every obstacle of every scene: as many rows as the distribution can need
    scene_slots = scene_config.max_obstacles if scenes_file is None else scenes_file.obstacles.shape[1]
    scene_slots = max(scene_slots, MAX_OBSTACLES, min_scene_slots)
    t0 = time.perf_counter()
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n, desc=f"PAC episodes (shard {shard_index + 1}/{num_shards})", unit="ep")
    # Simulate a little more than needed (PAC keeps ~98 %), but never more than batch_size at once.
    gen = Generator(
        params,
        min(batch_size, int(np.ceil(n * 1.05)) + 2),
        obstacle_encoding,
        workers,
        scene_config,
        scene_slots,
    )
    frames_total = 0
    ds = None
    finalized = False
    try:
        ds = LeRobotDataset.create(
            repo_id=repo_id,
            fps=FPS,
            features=dataset_features(obstacle_encoding, scene_slots),
            root=tmp,
            use_videos=False,
        )
        start = 0 if scenes_file is not None else seed
        skip = skip_noop_image_embedding(ds.meta.features) if fast_write else contextlib.nullcontext()
        episodes_iter = gen.episodes(
            seed_stream(start, num_shards, shard_index), n, scenes_file, bar.update if bar else None
        )
        with skip, contextlib.closing(episodes_iter):  # closing stops the workers at once, on any exit
            for frames in episodes_iter:
                frames_total += len(frames["action"])
                write_episode(ds, frames, fast=fast_write)
            ds.finalize()
            finalized = True
        if ds.meta.total_episodes == 0:
            raise RuntimeError("PAC produced no successful episode: nothing to write")
        extra = {
            "obstacle_encoding": obstacle_encoding,
            "scene_preset": scene_preset,
            "seed": seed,
            "num_shards": num_shards,
            "shard_index": shard_index,
            "fast_write": fast_write,
            "requested_episodes": n,
        }
        return _publish(tmp, root, ds, gen, t0, overwrite, extra, repo_id)
    except BaseException:  # any exit, SystemExit of SIGTERM included (main()): leave nothing behind
        if (
            ds is not None and not finalized
        ):  # close LeRobot's parquet writers, or they write into tmp on exit
            with contextlib.suppress(Exception):
                ds.finalize()
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        if bar is not None:
            bar.close()


def _publish(
    tmp: Path, root: Path, ds, gen: Generator, t0: float, overwrite: bool, summary_extra: dict, repo_id: str
) -> dict:
    """Write the summary files into the finished dataset ``tmp`` and move it to ``root``."""
    summary = {
        "repo_id": repo_id,
        "episodes": int(ds.meta.total_episodes),
        "frames": int(ds.meta.total_frames),
        "pac_attempted": gen.attempted,
        "pac_succeeded": gen.succeeded,
        "pac_success_rate": gen.succeeded / max(gen.attempted, 1),
        "seconds": time.perf_counter() - t0,
        **summary_extra,
    }
    # LeRobot writes stats.json keys in set order, which varies between runs: sort them.
    stats_path = tmp / "meta" / "stats.json"
    stats_path.write_text(json.dumps(json.loads(stats_path.read_text()), indent=4, sort_keys=True))
    (tmp / "meta" / "generation.json").write_text(json.dumps(summary, indent=1))
    if root.exists() and not overwrite:  # checked again: it appeared while this run was generating
        raise FileExistsError(
            f"destination {root} appeared while this run was generating (another generation?); "
            "nothing was replaced: pass --overwrite to replace it"
        )
    if root.exists():  # --overwrite: swap, then delete the old one
        trash = root.parent / f"{_old_prefix(root)}{os.getpid()}"
        os.rename(root, trash)
        try:
            rename_noreplace(tmp, root)
        except BaseException:
            with contextlib.suppress(OSError):
                os.rename(trash, root)  # put the old one back
            raise
        shutil.rmtree(trash, ignore_errors=True)
    else:
        rename_noreplace(tmp, root)
    summary["mb"] = sum(f.stat().st_size for f in root.rglob("*") if f.is_file()) / 1e6
    summary["seconds"] = time.perf_counter() - t0
    return summary


# -- hub-style folder --------------------------------------------------------------------------------
def dataset_card(summary: dict, features: dict, command: str) -> str:
    feats = "\n".join(
        f"- `{k}`: {v['dtype']} {list(v['shape'])}"
        + (f" ({', '.join(v['names'][:7])}...)" if v["names"] else "")
        for k, v in features.items()
    )
    return f"""---
license: apache-2.0
task_categories:
- robotics
tags:
- LeRobot
- lerobot_formation
- formation-control
- multi-agent
- simulation
configs:
- config_name: default
  data_files: data/*/*.parquet
pretty_name: Formation navigation PAC demonstrations
---

# Formation navigation: PAC demonstrations

This dataset was created with [LeRobot](https://github.com/huggingface/lerobot) (format v3.0) by
`lerobot_formation`. A team of four robots (two leaders as a rigid bar, two followers keeping a
square with a distance-based law) crosses a field of 3-5 circular obstacles to the goal (5, 5).
The demonstrator is the Path-Aware Controller (PAC), a potential-field controller with a path
check, a cost-to-go detour and a whole-formation footprint governor. Only successful episodes are
kept.

- Episodes: {summary["episodes"]}, frames: {summary["frames"]}, fps: {FPS}
- PAC success rate while generating: {summary["pac_success_rate"]:.1%} ({summary["pac_succeeded"]} of {summary["pac_attempted"]} scenes)
- Scene seeds: from {summary["seed"]} (shard {summary["shard_index"] + 1} of {summary["num_shards"]}); every
  episode's scene is stored in its `scene.*` columns.
- Observation encoding: `{summary["obstacle_encoding"]}`

## Features
{feats}

## How it was generated
```
{command}
```

## Load it offline
```python
import os
os.environ["HF_LEROBOT_HOME"] = "<the folder that holds {summary["repo_id"]}>"
from lerobot.datasets.lerobot_dataset import LeRobotDataset
ds = LeRobotDataset("{summary["repo_id"]}")
```
"""


def _git_blob_sha(data: bytes) -> str:
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


def push_to_folder(
    root: Path, hub_dir: Path, repo_id: str, summary: dict, command: str, overwrite: bool
) -> Path:
    """Lay the dataset out as a hub dataset repository under ``hub_dir``.

    - ``hub_dir/<repo_id>/``: ``meta/``, ``data/`` and a ``README.md`` dataset card; this is what
      ``HF_LEROBOT_HOME=hub_dir`` + ``LeRobotDataset(repo_id)`` loads offline.
    - ``hub_dir/hub/datasets--<owner>--<name>/``: the same files as ``huggingface_hub`` caches a hub
      revision (``blobs/``, ``snapshots/<revision>/``, ``refs/main`` and the LeRobot codebase tag
      ``refs/v3.0``), so ``snapshot_download(..., revision="v3.0", local_files_only=True)`` resolves it.
      The revision is a deterministic hash of the files (only the hub can assign a real commit id).
    """
    dest = Path(hub_dir) / repo_id
    owner, name = repo_id.split("/")
    cache = Path(hub_dir) / "hub" / f"datasets--{owner}--{name}"
    if (dest.exists() or cache.exists()) and not overwrite:
        raise FileExistsError(f"hub folder {dest} already exists; pass --overwrite to replace it")
    tmp = dest.parent / f".{dest.name}.tmp-{os.getpid()}"
    tmp_cache = cache.parent / f".{cache.name}.tmp-{os.getpid()}"
    for t in (tmp, tmp_cache):
        shutil.rmtree(t, ignore_errors=True)
        t.parent.mkdir(parents=True, exist_ok=True)
    try:
        shutil.copytree(root, tmp)
        info = json.loads((tmp / "meta" / "info.json").read_text())
        (tmp / "README.md").write_text(dataset_card(summary, info["features"], command))
        files = sorted(p for p in tmp.rglob("*") if p.is_file())
        blobs = {p.relative_to(tmp).as_posix(): _git_blob_sha(p.read_bytes()) for p in files}
        revision = hashlib.sha1("\n".join(f"{k} {v}" for k, v in blobs.items()).encode()).hexdigest()
        for rel, blob in blobs.items():
            target = tmp_cache / "blobs" / blob
            target.parent.mkdir(parents=True, exist_ok=True)
            if not target.exists():
                shutil.copyfile(tmp / rel, target)
            link = tmp_cache / "snapshots" / revision / rel
            link.parent.mkdir(parents=True, exist_ok=True)
            link.symlink_to(os.path.relpath(target, link.parent))
        (tmp_cache / "refs").mkdir()
        (tmp_cache / "refs" / "main").write_text(revision)
        (tmp_cache / "refs" / info["codebase_version"]).write_text(revision)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(tmp_cache, ignore_errors=True)
        raise
    for final, staged in ((dest, tmp), (cache, tmp_cache)):
        if final.exists():
            shutil.rmtree(final)
        os.rename(staged, final)
    return dest


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        prog="lerobot-formation-generate", description="PAC demonstrations as a LeRobot dataset (v3.0)."
    )
    ap.add_argument(
        "--episodes", type=int, default=PAPER_EPISODES, help="successful episodes to keep (all shards)"
    )
    ap.add_argument("--seed", type=int, default=0, help="first scene seed")
    ap.add_argument(
        "--repo-id",
        default="local/formation_pac",
        help="dataset id 'owner/name', as LeRobotDataset(repo_id) loads it; also the default --root's name",
    )
    ap.add_argument("--root", default=None, help="dataset folder (default: $HF_LEROBOT_HOME/<repo-id>)")
    ap.add_argument("--scenes", default=None, help="scenes JSON file to use instead of random seeds")
    ap.add_argument(
        "--obstacle-encoding",
        default="grid",
        choices=ENCODINGS,
        help="observation.environment_state: 'grid' (the paper's 7x7 radius grid + goal, 51 values), "
        "'grid+list' (plus the obstacles [x, y, r], 66; the CPU config's) or another encoding of "
        "core/obstacle_grid.py; must match the policy trained on it",
    )
    ap.add_argument(
        "--scene-slots",
        type=int,
        default=0,
        help="at least this many obstacle rows in scene.obstacles (to merge with a dataset of a wider "
        "preset, e.g. 15 for 'wide'); default: as many as the scenes need",
    )
    ap.add_argument(
        "--scene-preset",
        default="paper",
        choices=tuple(SCENE_PRESETS),
        help="scene distribution: 'paper' (SPEC's), or wider ones (core/scene.py SCENE_PRESETS)",
    )
    ap.add_argument(
        "--push-to", default=None, help="also lay the dataset out as a hub repo under this folder"
    )
    ap.add_argument(
        "--num-shards", type=int, default=1, help="split --episodes into this many independent datasets"
    )
    ap.add_argument("--shard-index", type=int, default=0, help="which shard to write, 0 .. --num-shards - 1")
    ap.add_argument("--batch-size", type=int, default=256, help="episodes simulated at once")
    ap.add_argument("--workers", type=int, default=1, help="simulation processes beside the writer (0: none)")
    ap.add_argument(
        "--slow-write", action="store_true", help="per-frame add_frame instead of episode buffers"
    )
    ap.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing --root (and --push-to copy); without it an existing one is an error",
    )
    ap.add_argument(
        "--no-progress",
        action="store_true",
        help="no progress bar (there is none either when stderr is not a terminal); the summary "
        "line is always printed",
    )
    add_threads_argument(ap, "CPU threads per process, which the data does not depend on")
    args = ap.parse_args(argv)
    if args.episodes < 1:
        ap.error(f"--episodes must be >= 1, got {args.episodes}")
    if args.seed < 0:
        ap.error(f"--seed must be >= 0, got {args.seed}")
    if args.num_shards < 1 or not 0 <= args.shard_index < args.num_shards:
        ap.error(f"need 0 <= --shard-index < --num-shards, got {args.shard_index} and {args.num_shards}")
    if args.workers < 0:
        ap.error(f"--workers must be >= 0, got {args.workers}")
    if args.batch_size < 1:
        ap.error(f"--batch-size must be >= 1, got {args.batch_size}")
    if "/" not in args.repo_id or args.repo_id.count("/") != 1:
        ap.error(f"--repo-id must look like 'owner/name', got {args.repo_id!r}")
    if args.scenes and not Path(args.scenes).is_file():
        ap.error(f"--scenes file {args.scenes} does not exist")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    apply_threads(args.threads)  # before lerobot loads torch, and inherited by the workers
    from lerobot_formation.plugin import quiet_torchcodec_warning

    quiet_torchcodec_warning()  # LeRobotDataset.create logs torchcodec's FFmpeg traceback otherwise
    if args.root is None:
        from lerobot.utils.constants import HF_LEROBOT_HOME

        args.root = str(Path(HF_LEROBOT_HOME) / args.repo_id)
    with exit_on_signals():
        return _run(args, argv)


@contextlib.contextmanager
def exit_on_signals():
    """SIGTERM (and SIGHUP) raise SystemExit(128 + signal) in the main thread, so every ``finally`` and
    ``except BaseException`` runs: the temporary folder is removed and the workers stopped. (SIGKILL
    cannot be caught: its workers die with it, see ``_die_with_parent``, and the next run removes its
    temporary folder, see ``remove_stale_temporaries``.)"""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise SystemExit(128 + signum)

    names = [n for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n)]
    previous = {n: signal.signal(getattr(signal, n), handler) for n in names}
    try:
        yield
    finally:
        for n, h in previous.items():
            signal.signal(getattr(signal, n), h)


def _run(args: argparse.Namespace, argv: list[str] | None) -> int:
    try:
        summary = generate(
            Path(args.root),
            args.repo_id,
            args.episodes,
            seed=args.seed,
            obstacle_encoding=args.obstacle_encoding,
            scenes_path=args.scenes,
            num_shards=args.num_shards,
            shard_index=args.shard_index,
            overwrite=args.overwrite,
            fast_write=not args.slow_write,
            batch_size=args.batch_size,
            progress=not args.no_progress and sys.stderr.isatty(),  # no bars in logs
            workers=args.workers,
            scene_preset=args.scene_preset,
            min_scene_slots=args.scene_slots,
        )
    except (FileExistsError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.push_to:
        command = "lerobot-formation-generate " + " ".join(sys.argv[1:] if argv is None else argv)
        try:
            dest = push_to_folder(
                Path(args.root), Path(args.push_to), args.repo_id, summary, command, args.overwrite
            )
        except FileExistsError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        summary["pushed_to"] = str(dest)
    if summary["episodes"] < summary["requested_episodes"]:
        print(
            f"warning: only {summary['episodes']} of the {summary['requested_episodes']} episodes asked for: "
            f"PAC succeeded on {summary['pac_succeeded']} of the {summary['pac_attempted']} scenes of {args.scenes}",
            file=sys.stderr,
        )
    print(
        f"episodes {summary['episodes']}, frames {summary['frames']}, {summary['mb']:.1f} MB, "
        f"PAC success while generating {summary['pac_success_rate']:.1%} "
        f"({summary['pac_succeeded']}/{summary['pac_attempted']}), {summary['seconds']:.1f} s -> {args.root}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
