"""A finished dataset laid out as a hub dataset repository (``--push-to``): the dataset with a
card, and the ``huggingface_hub`` cache layout of one revision, for offline loading."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

from lerobot_formation.data.dataset_frames import FPS
from lerobot_formation.data.safe_destination import check_inside, check_replaceable, check_repo_id


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

    Raises:
        ValueError: ``repo_id`` is not ``owner/name`` in the hub's grammar, or a destination would lie
            outside ``hub_dir``.
        FileExistsError: a destination exists and not ``overwrite``, or ``overwrite`` but it is not a
            folder this project wrote (``safe_destination.check_replaceable``); nothing is deleted.
    """
    dest, cache = hub_destinations(hub_dir, repo_id, overwrite)
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
        old = final.parent / f".{final.name}.old-{os.getpid()}"
        if os.path.lexists(final):
            check_replaceable(final, hub_cache=final == cache)  # again, right before replacing
            os.rename(final, old)
        os.rename(staged, final)
        if os.path.lexists(old):
            shutil.rmtree(old)
    return dest


def hub_destinations(hub_dir: Path, repo_id: str, overwrite: bool) -> tuple[Path, Path]:
    """The two folders ``push_to_folder`` writes under ``hub_dir`` (the dataset and its hub cache
    entry), checked: the repo id's grammar, both inside ``hub_dir``, and each either absent or (with
    ``overwrite``) replaceable. Raises ValueError or FileExistsError as ``push_to_folder``."""
    from huggingface_hub.file_download import repo_folder_name

    check_repo_id(repo_id)
    hub_dir = Path(hub_dir)
    dest = check_inside(hub_dir / repo_id, hub_dir, "hub folder")
    cache = check_inside(
        hub_dir / "hub" / repo_folder_name(repo_id=repo_id, repo_type="dataset"), hub_dir, "hub cache"
    )
    for folder, is_cache in ((dest, False), (cache, True)):
        if os.path.lexists(folder):
            if not overwrite:
                raise FileExistsError(f"hub folder {folder} already exists; pass --overwrite to replace it")
            check_replaceable(folder, hub_cache=is_cache)
    return dest, cache
