"""Fast windowed reads for low-dimensional LeRobot datasets (opt out: LEROBOT_FORMATION_FAST_READS=0).

LeRobot 0.6.1 reads each windowed key (``observation.*`` history, ``action`` chunk) with a separate
Hugging Face ``datasets`` query. For a low-dim dataset such a query costs ~2-3 ms, mostly
``Features`` deep copies and per-cell tensor conversion, so a diffusion sample costs 5-8 ms and the
trainer waits for data ~70-80 % of the time on 2 cores (benchmarks/bench_train_throughput.py).

This module replaces ``DatasetReader._query_hf_dataset`` with the same query on in-memory columns:
the first windowed read of a reader copies the queried numeric columns out of the (memory-mapped)
Arrow table once (~100 MB for the full PAC dataset), and each later query is a NumPy gather. Results
are the same tensors, bit for bit (``tests/plugin/test_fast_reads.py``). Readers with video keys
keep LeRobot's path. The patch is applied when the plugin is imported (``lerobot-train`` imports it
through the ``lerobot_env_formation`` shim) and is active in the process that reads data: use
``--num_workers=0`` (the reads become cheap enough), since spawned DataLoader workers do not import
the plugin and fall back to LeRobot's reader.
"""

from __future__ import annotations

import os

import numpy as np
import torch

_ENABLED = os.environ.get("LEROBOT_FORMATION_FAST_READS", "1") != "0"
_original = None


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
    return torch.from_numpy(np.ascontiguousarray(arr))


def _fast_query_hf_dataset(self, query_indices: dict[str, list[int]]) -> dict:
    if len(self._meta.video_keys) > 0 or self.hf_dataset is None or self.hf_dataset._indices is not None:
        return _original(self, query_indices)
    cache = self.__dict__.setdefault("_formation_columns", {})
    result: dict = {}
    for key, q_idx in query_indices.items():
        if key not in cache:
            try:
                cache[key] = _column_tensor(self.hf_dataset.data, key)
            except Exception:  # an unusual column type: LeRobot's own path
                return _original(self, query_indices)
        rel = (
            q_idx
            if self._absolute_to_relative_idx is None
            else [self._absolute_to_relative_idx[i] for i in q_idx]
        )
        result[key] = cache[key][torch.as_tensor(rel, dtype=torch.long)]
    return result


def install() -> bool:
    """Patch LeRobot's reader once; returns whether the fast path is active."""
    global _original
    if not _ENABLED:
        return False
    from lerobot.datasets.dataset_reader import DatasetReader

    if _original is None:
        _original = DatasetReader._query_hf_dataset
        DatasetReader._query_hf_dataset = _fast_query_hf_dataset
    return True


def uninstall() -> None:
    global _original
    if _original is not None:
        from lerobot.datasets.dataset_reader import DatasetReader

        DatasetReader._query_hf_dataset = _original
        _original = None


install()  # importing the plugin turns it on (unless LEROBOT_FORMATION_FAST_READS=0)
