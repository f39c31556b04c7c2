"""LeRobot internals are touched only on the tested LeRobot version; on another one the stock
behaviour runs, after one logged warning per use."""

import logging

import numpy as np
import pytest

from lerobot_formation.compat import fast_reads, lerobot_compat
from lerobot_formation.data.dataset_frames import dataset_features
from lerobot_formation.data.lerobot_writer import write_episode
from lerobot_formation.envs.env import TASK


@pytest.fixture
def untested(monkeypatch):
    """Pretend to run on a LeRobot release this plugin was not written for."""
    monkeypatch.setattr(lerobot_compat, "lerobot_version", lambda: "9.0.0")
    monkeypatch.setattr(lerobot_compat, "_warned", set())


def test_tested_version_is_the_installed_one():
    assert lerobot_compat.version_is_tested(), lerobot_compat.lerobot_version()


def test_untested_version_keeps_the_stock_reader(monkeypatch, caplog):
    from lerobot.datasets.dataset_reader import DatasetReader

    fast_reads.uninstall()
    stock = DatasetReader.get_item
    try:
        monkeypatch.setattr(lerobot_compat, "lerobot_version", lambda: "9.0.0")
        monkeypatch.setattr(lerobot_compat, "_warned", set())
        with caplog.at_level(logging.WARNING, logger=lerobot_compat.__name__):
            assert not fast_reads.install()
            assert not fast_reads.install()
        assert DatasetReader.get_item is stock
        assert lerobot_compat.stock_reader_method("get_item") is stock
        assert len(caplog.records) == 1 and "9.0.0" in caplog.records[0].getMessage()
    finally:
        monkeypatch.undo()
        fast_reads.install()  # as the plugin's import left it
    assert DatasetReader.get_item is fast_reads._fast_get_item
    assert lerobot_compat.stock_reader_method("get_item") is stock


def test_untested_version_embeds_images_and_writes_frame_by_frame(untested):
    from lerobot.datasets import dataset_writer

    stock = dataset_writer.embed_images
    with lerobot_compat.skip_noop_image_embedding(dataset_features()):
        assert dataset_writer.embed_images is stock

    class Recorder:  # the two LeRobotDataset calls of the stock path
        def __init__(self):
            self.frames, self.saved = [], []

        def add_frame(self, frame):
            self.frames.append(frame)

        def save_episode(self, **kwargs):
            self.saved.append(kwargs)

    frames = {"action": np.zeros((3, 2), np.float32), "observation.state": np.ones((3, 7), np.float32)}
    ds = Recorder()
    write_episode(ds, frames, fast=True)
    assert len(ds.frames) == 3 and ds.saved == [{}]
    assert ds.frames[0]["task"] == TASK and set(ds.frames[0]) == {"action", "observation.state", "task"}


def test_tested_version_skips_the_noop_embedding():
    from lerobot.datasets import dataset_writer

    stock = dataset_writer.embed_images
    with lerobot_compat.skip_noop_image_embedding(dataset_features()):
        assert dataset_writer.embed_images is not stock
    assert dataset_writer.embed_images is stock
    image = {"image": {"dtype": "image", "shape": (8, 8, 3), "names": None}}
    with lerobot_compat.skip_noop_image_embedding(image):
        assert dataset_writer.embed_images is stock


def test_weights_loaded_hook_runs_after_the_parent_load_and_is_off_for_another_signature(monkeypatch, caplog):
    """``add_weights_loaded_hook`` wraps the parent's ``_load_as_safetensor`` (subclasses included);
    a parent with other arguments keeps its own loading, after one logged warning."""
    monkeypatch.setattr(lerobot_compat, "_warned", set())
    calls = []

    class Stock:
        @classmethod
        def _load_as_safetensor(cls, model, model_file, map_location, strict):
            calls.append(("stock", cls.__name__, model_file))
            return model

    class Policy(Stock):
        pass

    class Child(Policy):
        pass

    lerobot_compat.add_weights_loaded_hook(Policy, lambda model, f: calls.append(("hook", f)) or model + 1)
    assert Child._load_as_safetensor(1, "w.safetensors", "cpu", False) == 2
    assert calls == [("stock", "Child", "w.safetensors"), ("hook", "w.safetensors")]

    class OtherStock:
        @classmethod
        def _load_as_safetensor(cls, model, model_file, device):
            return model

    class OtherPolicy(OtherStock):
        pass

    with caplog.at_level(logging.WARNING, logger=lerobot_compat.__name__):
        lerobot_compat.add_weights_loaded_hook(OtherPolicy, lambda model, f: model + 1)
    assert OtherPolicy._load_as_safetensor(1, "w.safetensors", "cpu") == 1
    assert "OtherPolicy loads without its check" in caplog.text


def test_queued_history_is_the_batch_until_observations_are_pushed():
    import torch
    from plugin_helpers import N_OBS, obs_batch, tiny_config

    from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy

    policy = FormationDiffusionPolicy(tiny_config())
    policy.reset()
    offline = {k: v[:, None].repeat(1, N_OBS, 1) for k, v in obs_batch().items()}
    assert lerobot_compat.queued_history(policy, offline) is offline
    first, second = obs_batch(seed=1), obs_batch(seed=2)
    lerobot_compat.push_observation(policy, first)
    lerobot_compat.push_observation(policy, second)
    history = lerobot_compat.queued_history(policy, first)
    for key in first:
        assert torch.equal(history[key], torch.stack([first[key], second[key]], dim=1))
