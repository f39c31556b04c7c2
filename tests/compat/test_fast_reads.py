"""Fast windowed reads give LeRobot's own items, bit for bit, and are much cheaper."""

import time

import numpy as np
import pytest
import torch

from lerobot_formation.compat import fast_reads
from lerobot_formation.data import lerobot_writer

REPO = "local/fast_reads"


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    r = tmp_path_factory.mktemp("fr") / "ds"
    lerobot_writer.generate(r, REPO, 6, progress=False)
    return r


def _items(root, idx, episodes=None, windows=True):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    fps, n_obs, horizon = 10, 2, 16
    delta = {
        "observation.state": [i / fps for i in range(1 - n_obs, 1)],
        "observation.environment_state": [i / fps for i in range(1 - n_obs, 1)],
        "action": [i / fps for i in range(1 - n_obs, 1 - n_obs + horizon)],
    }
    if not windows:
        delta = None
    ds = LeRobotDataset(REPO, root=root, delta_timestamps=delta, episodes=episodes)
    idx = [i for i in idx if i < len(ds)]
    t0 = time.perf_counter()
    out = [ds[i] for i in idx]
    return out, (time.perf_counter() - t0) / len(idx)


@pytest.mark.parametrize(("episodes", "windows"), [(None, True), ([1, 3, 4], True), (None, False)])
def test_fast_reads_equal_lerobot_reads(root, episodes, windows):
    # Episode starts and ends (padding on both sides) and random frames.
    idx = list(range(0, 40)) + list(np.random.default_rng(0).integers(0, 500, 60))
    fast_reads.install()
    fast, t_fast = _items(root, idx, episodes, windows)
    fast_reads.uninstall()
    try:
        slow, t_slow = _items(root, idx, episodes, windows)
    finally:
        fast_reads.install()
    for a, b in zip(fast, slow, strict=True):
        assert a.keys() == b.keys()
        for k in a:
            if isinstance(a[k], torch.Tensor):
                assert a[k].dtype == b[k].dtype and torch.equal(a[k], b[k]), k
            else:
                assert a[k] == b[k], k
    # their speed is benchmarks/bench_train_throughput.py --fast-reads's figure, not a timed test


def _collate_reporting_reader(items):
    """Runs in the DataLoader worker: the batch, and which get_item the worker's reader class has."""
    from lerobot.datasets.dataset_reader import DatasetReader
    from torch.utils.data import default_collate

    return default_collate(items), DatasetReader.get_item.__name__


def test_spawned_workers_get_the_fast_path(root):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    delta = {"action": [i / 10 for i in range(-1, 15)]}
    fast_reads.install()
    ds = LeRobotDataset(REPO, root=root, delta_timestamps=delta)
    ds[0]  # builds the main process's table, which must not travel to the worker
    loader = torch.utils.data.DataLoader(
        ds,
        batch_size=8,
        num_workers=1,
        multiprocessing_context="spawn",
        collate_fn=_collate_reporting_reader,
    )
    batch, worker_get_item = next(iter(loader))
    assert worker_get_item == "_fast_get_item"
    expected = torch.stack([ds[i]["action"] for i in range(8)])
    assert torch.equal(batch["action"], expected)
    fast_reads.uninstall()
    try:  # and the stock reader stays stock in its workers when the plugin is off
        ds2 = LeRobotDataset(REPO, root=root, delta_timestamps=delta)
        assert "_formation_fast_reads" not in ds2.reader.__getstate__()
    finally:
        fast_reads.install()
