"""Fast windowed reads for low-dimensional LeRobot datasets (opt out: LEROBOT_FORMATION_FAST_READS=0).

LeRobot 0.6.1 reads each windowed key (``observation.*`` history, ``action`` chunk) with a separate
Hugging Face ``datasets`` query. For a low-dim dataset such a query costs ~2-3 ms, mostly
``Features`` deep copies and per-cell tensor conversion, so a diffusion sample costs 5-8 ms and the
trainer waits for data ~70-80 % of the time on 2 cores (benchmarks/bench_train_throughput.py).

Even with the windows fixed, the rest of ``DatasetReader.get_item`` costs ~0.3 ms a sample: the base
row through ``datasets`` (``Features`` copies, ``hf_transform_to_torch`` per cell), the episode's
bounds as a row of the episodes ``Dataset`` and Python list comprehensions for the window indices.

This module replaces two ``DatasetReader`` methods for low-dimensional readers (no video, no image
or depth feature, no image transforms):

- ``get_item``: every numeric column is copied once out of the (memory-mapped) Arrow table into a
  tensor (~150 MB for the full PAC dataset), episode bounds into two arrays; a sample is then a few
  tensor gathers. Same keys, values, dtypes and shapes as LeRobot's, bit for bit
  (``tests/compat/test_fast_reads.py``); integers come out as int64 and floats as float32, as
  ``hf_transform_to_torch``'s ``torch.tensor(python value)`` gives them.
- ``_query_hf_dataset`` (used by LeRobot's ``get_item`` for readers the fast path does not take,
  e.g. with image features stored in the table or image transforms): the same windowed query on
  in-memory columns.

Only readers of our own datasets take it (``reader_is_ours``: the PAC dataset's ``scene.*``
features); any other reader (another project's dataset, videos, images, string columns) keeps
LeRobot's path. Importing the plugin patches nothing: ``install()`` runs when a formation policy is
made (``FormationDiffusionPolicy.__init__``: ``lerobot-train``, ``lerobot-eval``, the engine), through
``lerobot_compat.patch_dataset_reader``; on a LeRobot
version other than the tested one it is not applied (one logged warning) and LeRobot's reader runs
as shipped. DataLoader workers (``--num_workers>0``, spawned) never import the plugin themselves, so
a pickled reader of ours carries a small marker object of this module: unpickling it in a worker
installs the fast path there too. The in-memory table is not pickled; each worker builds
its own on its first read.
"""

from __future__ import annotations

import os

import numpy as np
import torch

from lerobot_formation.compat import lerobot_compat

_ENABLED = os.environ.get("LEROBOT_FORMATION_FAST_READS", "1") != "0"


def _column_tensor(table, key: str) -> torch.Tensor:
    """One Arrow column as a (rows, ...) tensor, as ``hf_transform_to_torch`` would give per row."""
    import pyarrow as pa

    col = table.column(key).combine_chunks()
    if (
        pa.types.is_list(col.type)
        or pa.types.is_fixed_size_list(col.type)
        or pa.types.is_large_list(col.type)
    ):
        values = col.flatten().to_numpy(zero_copy_only=False)
        arr = values.reshape(len(col), -1)
    else:
        arr = col.to_numpy(zero_copy_only=False)
    # hf_transform_to_torch builds torch.tensor(python value): int64 for integers, float32 for floats.
    if arr.dtype.kind in "iu":
        arr = arr.astype(np.int64, copy=False)
    elif arr.dtype.kind == "f":
        arr = arr.astype(np.float32, copy=False)
    elif arr.dtype.kind != "b":
        raise TypeError(f"column {key!r} of dtype {arr.dtype} is not numeric")
    arr = np.ascontiguousarray(arr)
    return torch.from_numpy(arr if arr.flags.writeable else arr.copy())


class _LowDimTable:
    """A reader's columns and episode bounds in memory (built on its first fast read)."""

    def __init__(self, reader):
        table = reader.hf_dataset.data
        self.columns = {key: _column_tensor(table, key) for key in table.column_names}
        episodes = lerobot_compat.reader_meta(reader).episodes
        ep_index = np.asarray(episodes.data.column("episode_index").to_numpy(), dtype=np.int64)
        n = int(ep_index.max()) + 1 if len(ep_index) else 0
        self.ep_from = np.zeros(n, np.int64)
        self.ep_to = np.zeros(n, np.int64)
        self.ep_from[ep_index] = episodes.data.column("dataset_from_index").to_numpy()
        self.ep_to[ep_index] = episodes.data.column("dataset_to_index").to_numpy()
        self.deltas = {k: np.asarray(d, dtype=np.int64) for k, d in (reader.delta_indices or {}).items()}
        # Selected episodes only: the table's rows are relative, the windows absolute.
        self.abs_to_rel = None
        if lerobot_compat.reader_relative_rows(reader) is not None:
            absolute = self.columns["index"].numpy()
            self.abs_to_rel = np.full(int(absolute.max()) + 1, -1, np.int64)
            self.abs_to_rel[absolute] = np.arange(len(absolute))
        self.tasks: dict[int, str] = {}


# Every PAC dataset has these features (``data.dataset_frames.dataset_features``): the fast path takes
# only readers of such datasets; any other dataset reads through LeRobot's own methods, untouched.
OUR_FEATURES = ("scene.seed", "scene.obstacles", "scene.goal", "scene.start")


def reader_is_ours(reader) -> bool:
    """Whether ``reader`` reads a formation dataset (all of ``OUR_FEATURES``)."""
    features = lerobot_compat.reader_meta(reader).features
    return all(key in features for key in OUR_FEATURES)


def _unpickled_marker() -> _FastReadsMarker:
    install()
    return _FastReadsMarker()


class _FastReadsMarker:
    """Pickled with each reader of ours: unpickling it (in a DataLoader worker) installs the fast path."""

    def __reduce__(self):
        return _unpickled_marker, ()


_CACHES = ("_formation_table", "_formation_columns")  # per process, rebuilt on the first read


def _getstate(self) -> dict:
    state = {k: v for k, v in self.__dict__.items() if k not in _CACHES}
    if reader_is_ours(self):
        state["_formation_fast_reads"] = _FastReadsMarker()
    return state


def _fast_get_item(self, idx) -> dict:
    table = self.__dict__.get("_formation_table")
    if table is None:
        if (
            self.__dict__.get("_formation_slow")
            or not reader_is_ours(self)
            or not lerobot_compat.reader_is_low_dim(self)
        ):
            return lerobot_compat.stock_reader_method("get_item")(self, idx)
        try:
            table = self._formation_table = _LowDimTable(self)
        except (TypeError, KeyError, ValueError):  # an unusual column: LeRobot's own path
            self._formation_slow = True
            return lerobot_compat.stock_reader_method("get_item")(self, idx)
    idx = int(idx)
    item = {key: col[idx] for key, col in table.columns.items()}
    if table.deltas:
        ep = int(item["episode_index"])
        abs_idx = int(item["index"])
        start, end = table.ep_from[ep], table.ep_to[ep]
        for key, delta in table.deltas.items():
            q = abs_idx + delta
            rows = np.clip(q, start, end - 1)
            if table.abs_to_rel is not None:
                rows = table.abs_to_rel[rows]
            item[key] = table.columns[key][torch.from_numpy(rows)]
            item[f"{key}_is_pad"] = torch.from_numpy((q < start) | (q >= end))
    task_idx = int(item["task_index"])
    task = table.tasks.get(task_idx)
    if task is None:
        task = table.tasks[task_idx] = lerobot_compat.reader_meta(self).tasks.iloc[task_idx].name
    item["task"] = task
    return item


def _fast_query_hf_dataset(self, query_indices: dict[str, list[int]]) -> dict:
    if (
        not reader_is_ours(self)
        or len(lerobot_compat.reader_meta(self).video_keys) > 0
        or not lerobot_compat.reader_table_is_plain(self)
    ):
        return lerobot_compat.stock_reader_method("_query_hf_dataset")(self, query_indices)
    cache = self.__dict__.setdefault("_formation_columns", {})
    result: dict = {}
    for key, q_idx in query_indices.items():
        if key not in cache:
            try:
                cache[key] = _column_tensor(self.hf_dataset.data, key)
            except Exception:  # an unusual column type: LeRobot's own path
                return lerobot_compat.stock_reader_method("_query_hf_dataset")(self, query_indices)
        relative = lerobot_compat.reader_relative_rows(self)
        rel = q_idx if relative is None else [relative[i] for i in q_idx]
        result[key] = cache[key][torch.as_tensor(rel, dtype=torch.long)]
    return result


def install() -> bool:
    """Patch LeRobot's reader once (``lerobot_compat.patch_dataset_reader``); returns whether the fast
    path is active (not with LEROBOT_FORMATION_FAST_READS=0, nor on an untested LeRobot version)."""
    if not _ENABLED:
        return False
    return lerobot_compat.patch_dataset_reader(_fast_get_item, _fast_query_hf_dataset, _getstate)


def uninstall() -> None:
    lerobot_compat.unpatch_dataset_reader()
