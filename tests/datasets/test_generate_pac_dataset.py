"""The PAC dataset: round trip, windows, determinism, interruption, hub folder, stock tools."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import dataset_file_hashes

from datasets_scripts import generate_pac_dataset as gen
from lerobot_formation.core.controllers.pac import PACController
from lerobot_formation.core.episodes.rollout import rollout
from lerobot_formation.core.world.sampling import sample_scenes
from lerobot_formation.core.world.scenes import scenes_from_frames
from lerobot_formation.data import lerobot_writer
from lerobot_formation.data.dataset_frames import episode_frames
from lerobot_formation.data.hub_folder import push_to_folder
from lerobot_formation.envs.env import TASK

REPO = "local/formation_test"
N = 5  # episodes: the split below gives 4 and 1


def _generate(root: Path, **kw):
    return lerobot_writer.generate(root, REPO, N, progress=False, **kw)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """The dataset the tests share, simulated inline (``workers=0``: no worker process to start); the
    pipelined simulation must write the same bytes (``test_same_seed_gives_byte_identical_files``)."""
    root = tmp_path_factory.mktemp("ds") / "formation_test"
    _generate(root, workers=0)
    return root


def test_round_trip_through_lerobot_dataset(tiny):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(REPO, root=tiny)
    assert ds.meta.total_episodes == N
    assert ds.fps == 10
    for key, shape in (
        ("observation.state", (7,)),
        ("observation.environment_state", (51,)),
        ("action", (2,)),
    ):
        assert tuple(ds.meta.features[key]["shape"]) == shape
        assert ds.meta.features[key]["dtype"] == "float32"
        assert ds.meta.features[key]["names"]
    # The stored episode is PAC's rollout on the stored scene.
    ep = ds.meta.episodes[0]
    item = ds[int(ep["dataset_from_index"])]
    seed = int(item["scene.seed"])
    scene = sample_scenes([seed])
    rec = rollout(scene, PACController())
    frames = episode_frames(rec, scene, 0, "grid")
    n = int(ep["length"])
    assert n == len(frames["action"])
    for t in (0, 1, n // 2, n - 1):
        it = ds[int(ep["dataset_from_index"]) + t]
        for key in ("observation.state", "observation.environment_state", "action"):
            np.testing.assert_array_equal(it[key].numpy(), frames[key][t])
    assert item["task"] == TASK


def test_scenes_rebuild_from_frames(tiny):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(REPO, root=tiny)
    first = [ds[int(e["dataset_from_index"])] for e in ds.meta.episodes]
    scenes = scenes_from_frames(
        np.stack([f["scene.obstacles"].numpy() for f in first]),
        np.stack([f["scene.goal"].numpy() for f in first]),
        np.stack([f["scene.start"].numpy() for f in first]),
        np.array([int(f["scene.seed"]) for f in first]),
    )
    ref = sample_scenes(scenes.seeds)
    np.testing.assert_allclose(scenes.obstacles[scenes.mask], ref.obstacles[ref.mask], atol=1e-6)


def test_diffusion_windows_and_padding(tiny):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    fps, n_obs, horizon = 10, 2, 64
    delta = {
        "observation.state": [i / fps for i in range(1 - n_obs, 1)],
        "observation.environment_state": [i / fps for i in range(1 - n_obs, 1)],
        "action": [i / fps for i in range(1 - n_obs, 1 - n_obs + horizon)],
    }
    ds = LeRobotDataset(REPO, root=tiny, delta_timestamps=delta)
    plain = LeRobotDataset(REPO, root=tiny)
    ep = ds.meta.episodes[1]
    start, end = int(ep["dataset_from_index"]), int(ep["dataset_to_index"])
    first = ds[start]
    assert first["observation.state"].shape == (2, 7)
    assert first["action"].shape == (64, 2)
    assert first["observation.state_is_pad"].tolist() == [True, False]
    np.testing.assert_array_equal(first["observation.state"][0], first["observation.state"][1])  # copy-padded
    mid = ds[start + 5]
    np.testing.assert_array_equal(mid["observation.state"][0], plain[start + 4]["observation.state"])
    np.testing.assert_array_equal(mid["action"][1], plain[start + 5]["action"])
    np.testing.assert_array_equal(mid["action"][10], plain[start + 14]["action"])
    last = ds[end - 3]
    pad = last["action_is_pad"].numpy()
    assert not pad[:4].any() and pad[4:].all()  # frames end-4 .. end-1 exist, the rest is padding
    np.testing.assert_array_equal(last["action"][-1], plain[end - 1]["action"])


def test_same_seed_gives_byte_identical_files(tiny, tmp_path):
    """Another run of the same seed, simulated pipelined in a worker process (the default), writes
    the inline run's files byte for byte."""
    again = tmp_path / "again"
    _generate(again)
    assert dataset_file_hashes(again) == dataset_file_hashes(tiny)


def test_fast_writer_equals_add_frame_loop(tiny, tmp_path):
    import pyarrow.parquet as pq

    slow = tmp_path / "slow"
    _generate(slow, fast_write=False, workers=0)
    a = pq.read_table(tiny / "data/chunk-000/file-000.parquet")
    b = pq.read_table(slow / "data/chunk-000/file-000.parquet")
    assert a.equals(b)  # same columns and values; only the HF schema fingerprint differs


def test_interrupted_run_leaves_nothing_and_rerun_works(tmp_path, monkeypatch):
    root = tmp_path / "ds"
    calls = {"n": 0}
    real = lerobot_writer.write_episode

    def interrupting(ds, frames, fast=True):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        real(ds, frames, fast)

    monkeypatch.setattr(lerobot_writer, "write_episode", interrupting)
    with pytest.raises(KeyboardInterrupt):
        _generate(root)
    assert not root.exists()
    assert list(tmp_path.iterdir()) == []  # no temporary folder left behind either
    monkeypatch.setattr(lerobot_writer, "write_episode", real)
    assert _generate(root, workers=0)["episodes"] == N


def test_existing_destination_needs_overwrite(tiny, capsys):
    assert gen.main(["--episodes", "2", "--root", str(tiny), "--no-progress"]) == 2
    assert "already exists" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["--episodes", "0"], "--episodes must be >= 1, got 0"),
        (["--num-shards", "2", "--shard-index", "2"], "--shard-index"),
        (["--repo-id", "noslash"], "owner/name"),
        (["--scenes", "/does/not/exist.json"], "does not exist"),
        (["--obstacle-encoding", "pixels"], "invalid choice"),
    ],
)
def test_bad_arguments(argv, match, capsys):
    with pytest.raises(SystemExit):
        gen.parse_args(argv)
    assert match in capsys.readouterr().err


def test_hub_folder_card_and_offline_load(tiny, tmp_path, monkeypatch):
    summary = json.loads((tiny / "meta" / "generation.json").read_text())
    dest = push_to_folder(tiny, tmp_path / "hub", REPO, summary, "lerobot-formation-generate ...", False)
    assert dest == tmp_path / "hub" / REPO
    text = (dest / "README.md").read_text()
    front = yaml.safe_load(text.split("---")[1])
    assert front["license"] == "apache-2.0"
    assert "robotics" in front["task_categories"] and "LeRobot" in front["tags"]
    assert "PAC success rate while generating" in text
    from huggingface_hub import snapshot_download

    snap = snapshot_download(
        REPO, repo_type="dataset", revision="v3.0", cache_dir=tmp_path / "hub" / "hub", local_files_only=True
    )
    assert (Path(snap) / "meta" / "info.json").read_bytes() == (dest / "meta" / "info.json").read_bytes()
    # Offline load by repo id through HF_LEROBOT_HOME, in a fresh interpreter.
    code = (
        "from lerobot.datasets.lerobot_dataset import LeRobotDataset;"
        f"ds = LeRobotDataset('{REPO}'); print(ds.meta.total_episodes)"
    )
    env = {"HF_LEROBOT_HOME": str(tmp_path / "hub"), "HF_HUB_OFFLINE": "1", "PATH": "/usr/bin:/bin"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == str(N)


def _edit_dataset(monkeypatch, *args: str) -> None:
    """LeRobot's ``lerobot-edit-dataset`` with these arguments: its entry point as the console script
    calls it (the draccus parse of ``sys.argv``), in this process: a fresh interpreter would only add
    the seconds of importing LeRobot."""
    from lerobot.scripts.lerobot_edit_dataset import edit_dataset

    monkeypatch.setattr(sys, "argv", ["lerobot-edit-dataset", *args])
    edit_dataset()


def test_split_and_merge_with_lerobot_edit_dataset(tiny, tmp_path, monkeypatch):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    split_root = tmp_path / "split"
    _edit_dataset(
        monkeypatch, "--repo_id", REPO, "--root", str(tiny), "--new_root", str(split_root),
        "--operation.type", "split", "--operation.splits", '{"train": 0.8, "val": 0.2}',
    )  # fmt: skip
    parts = sorted(p for p in split_root.iterdir() if p.is_dir())
    sizes = [LeRobotDataset(f"{REPO}_{p.name}", root=p).meta.total_episodes for p in parts]
    assert sum(sizes) == N and len(sizes) == 2
    merged = tmp_path / "merged"
    _edit_dataset(
        monkeypatch, "--new_repo_id", "local/merged", "--new_root", str(merged), "--operation.type", "merge",
        "--operation.repo_ids", str([f"{REPO}_{p.name}" for p in parts]),
        "--operation.roots", str([str(p) for p in parts]),
    )  # fmt: skip
    m = LeRobotDataset("local/merged", root=merged)
    assert m.meta.total_episodes == N
    seeds = sorted({int(m[int(e["dataset_from_index"])]["scene.seed"]) for e in m.meta.episodes})
    orig = LeRobotDataset(REPO, root=tiny)
    assert seeds == sorted(
        {int(orig[int(e["dataset_from_index"])]["scene.seed"]) for e in orig.meta.episodes}
    )


def test_shards_are_valid_and_disjoint(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    seeds = []
    for i in range(2):
        root = tmp_path / f"shard{i}"
        lerobot_writer.generate(root, REPO, 6, num_shards=2, shard_index=i, workers=0, progress=False)
        ds = LeRobotDataset(REPO, root=root)
        assert ds.meta.total_episodes == 3
        seeds.append({int(ds[int(e["dataset_from_index"])]["scene.seed"]) for e in ds.meta.episodes})
    assert not seeds[0] & seeds[1]
