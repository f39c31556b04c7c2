"""The PAC dataset through LeRobot's own writer (``LeRobotDataset.create`` -> ``save_episode`` ->
``finalize``), into a temporary folder renamed into place with its summary files."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from lerobot_formation.compat.lerobot_compat import save_episode_buffer, skip_noop_image_embedding
from lerobot_formation.core.perception.conditions import RANDOMIZE_ON, Conditions
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.core.world.presets import distribution_slots
from lerobot_formation.core.world.scene_files import load_scenes
from lerobot_formation.data.dataset_frames import ACTION, FPS, MAX_OBSTACLES, dataset_features
from lerobot_formation.data.pac_episodes import (
    CONDITION_GROUP,
    EpisodeRecipe,
    ExpertFactory,
    Generator,
    seed_stream,
    shard_episodes,
)
from lerobot_formation.data.safe_destination import (
    check_replaceable,
    remove_stale_temporaries,
    rename_noreplace,
    temporary_path,
    trash_path,
)
from lerobot_formation.envs.env import TASK


def write_episode(ds, frames: dict[str, np.ndarray], fast: bool = True) -> None:
    """Write one episode through LeRobot's writer. ``fast`` hands ``save_episode`` a pre-built episode
    buffer (``lerobot_compat.save_episode_buffer``) instead of a per-frame ``add_frame`` loop; the
    frames are identical either way. On an untested LeRobot version the loop runs."""
    if fast and save_episode_buffer(ds, frames, TASK):
        return
    for t in range(len(frames[ACTION])):
        ds.add_frame({**{k: v[t] for k, v in frames.items()}, "task": TASK})
    ds.save_episode()


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
    conditions: Conditions | None = None,
    expert: str = "pac",
    randomize: Conditions | None = None,
    policy_expert: ExpertFactory | None = None,
) -> dict:
    """Generate the dataset at ``root`` (atomically) and return a summary dict; ``conditions``: the
    episodes under realistic conditions (``core.perception.conditions``; None or all off: none); ``expert``:
    "pac" (on the perception), "privileged" (on the true world) or "policy" (the controllers
    ``policy_expert`` makes, e.g. ``bench.controllers.PolicyExpert``; ``workers`` must be 0), ``pac_episodes.EXPERTS``;
    ``randomize``: each group of seeds under its own draw of conditions up to these
    (``pac_episodes``; not with ``conditions``). ``scene_preset``: a
    ``core.world.sampling.sample_distribution`` spec (a preset, a mixture or a comma list).

    Raises:
        FileExistsError: ``root`` exists and not ``overwrite``, or ``overwrite`` but ``root`` is not a
            folder this project wrote (``safe_destination.check_replaceable``; checked at the start and
            again right before the replacement). Nothing is deleted then.
    """
    import datasets as hf_datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    hf_datasets.disable_progress_bars()  # one bar per episode otherwise

    root = Path(root)
    if root.exists() and not overwrite:
        raise FileExistsError(f"destination {root} already exists; pass --overwrite to replace it")
    if overwrite:
        check_replaceable(root)  # before any work: only a dataset this project wrote is replaced
    recipe = EpisodeRecipe(  # checked here, before any work; its scene_slots once the scenes are known
        obstacle_encoding,
        scene_preset,
        conditions=conditions,
        expert=expert,
        randomize=randomize,
        policy_expert=policy_expert,
    )
    distribution_slots(scene_preset)  # a ValueError naming a bad preset, before any work
    n = shard_episodes(episodes, num_shards, shard_index)
    root.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(root)  # of killed runs; refuses if a live generation writes root
    tmp = temporary_path(root)
    if tmp.exists():
        shutil.rmtree(tmp)
    params = FormationParams()
    scenes_file = load_scenes(scenes_path) if scenes_path else None
    if scenes_file is not None:
        held = len(range(shard_index, len(scenes_file), num_shards))  # this shard's scenes of the file
        if n > held:
            raise ValueError(
                f"--episodes {episodes} asks for more episodes than scenes file {scenes_path} holds "
                f"({len(scenes_file)} scenes{f', {held} of them in shard {shard_index}' if num_shards > 1 else ''})"
            )
    # scene.obstacles keeps every obstacle of every scene: as many rows as the distribution can need
    scene_slots = distribution_slots(scene_preset) if scenes_file is None else scenes_file.obstacles.shape[1]
    recipe = replace(recipe, scene_slots=max(scene_slots, MAX_OBSTACLES, min_scene_slots))
    t0 = time.perf_counter()
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n, desc=f"PAC episodes (shard {shard_index + 1}/{num_shards})", unit="ep")
    # Simulate a little more than needed (PAC keeps ~98 %), but never more than batch_size at once.
    gen = Generator(params, recipe, batch_size=min(batch_size, int(np.ceil(n * 1.05)) + 2), workers=workers)
    frames_total = 0
    ds = None
    finalized = False
    try:
        ds = LeRobotDataset.create(
            repo_id=repo_id,
            fps=FPS,
            features=dataset_features(obstacle_encoding, recipe.scene_slots),
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
                frames_total += len(frames[ACTION])
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
        if conditions is not None and conditions.enabled:
            extra["conditions"] = conditions.changed()
        if expert != "pac":
            extra["expert"] = expert
        if policy_expert is not None:
            extra["policy"] = policy_expert.source
        if randomize is not None:
            extra["conditions_randomize"] = {
                "ceiling": randomize.changed(),
                "p_on": RANDOMIZE_ON,
                "group": CONDITION_GROUP,
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
        check_replaceable(root)  # again: it may have changed while this run was generating
        trash = trash_path(root)
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
