"""The one place that touches LeRobot internals (names that are not LeRobot's public API).

Each use is checked against the LeRobot version it was written for (``TESTED``); on another version
the stock behaviour is used where one exists (with one logged warning per use), or a clear error
names what changed. The uses:

- ``global_conditioning``: ``DiffusionModel._prepare_global_conditioning`` (batched candidate sampling);
- ``use_conditioning_method`` / ``stock_global_conditioning`` / ``diffusion_unet``: a ``DiffusionModel``
  subclass that computes the conditioning itself (the obstacle-token encoder) overrides
  ``_prepare_global_conditioning`` and builds ``DiffusionConditionalUnet1d`` for its width;
- ``push_observation`` / ``queued_history``: ``DiffusionPolicy._queues``, the observation history
  ``select_action`` keeps (the safety layer's ``select_action`` and the lean ``predict_action_chunk``);
- ``add_weights_loaded_hook``: wraps ``PreTrainedPolicy._load_as_safetensor``, the one method that
  knows the weights file (the EMA check of ``formation_diffusion``);
- ``denoiser_parts``: what ``DiffusionModel.conditional_sample`` loops over (the U-Net, the noise
  scheduler, the step count), for the lean inference path (``inference_backend``);
- ``train_dataloader_worker_kwargs``: ``lerobot_train._dataloader_worker_kwargs`` (the training
  throughput benchmark builds lerobot-train's DataLoader);
- ``run_checks.install_train_checks``: wraps ``TrainPipelineConfig.validate`` (the offline
  ``--dataset.root`` check, the output lock, the resume report; it reads the checkpoint's step with
  ``lerobot.common.train_utils.load_training_step``);
- ``run_checks.install_eval_checks``: wraps ``EvalPipelineConfig.__post_init__`` (hands our env config
  the policy config it loads);
- ``run_checks.config_errors_in_draccus_messages``: wraps draccus's ``DecodingError.__str__``, the message that
  LeRobot's parser prints as ``error: ...``;
- ``patch_dataset_reader``: replaces ``DatasetReader.get_item`` / ``_query_hf_dataset`` with the fast
  low-dimensional reads of ``fast_reads.py``, which read the reader's private state through
  ``reader_meta``, ``reader_relative_rows`` and ``reader_is_low_dim``;
- ``skip_noop_image_embedding``: skips ``dataset_writer.embed_images`` for datasets without images;
- ``save_episode_buffer``: hands ``LeRobotDataset.save_episode`` a pre-built episode buffer (LeRobot's
  internal layout) instead of one ``add_frame`` call per frame;
- ``keep_final_eval_frame``: wraps ``lerobot_eval.rollout`` so eval videos end on the outcome frame.

"""

from __future__ import annotations

import contextlib
import inspect
import logging
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from torch import Tensor

TESTED = ("0.6.",)
logger = logging.getLogger(__name__)
_warned: set[str] = set()


def lerobot_version() -> str:
    import lerobot

    return getattr(lerobot, "__version__", "unknown")


def version_is_tested() -> bool:
    return lerobot_version().startswith(TESTED)


def _untested(what: str) -> bool:
    """True on a LeRobot version other than ``TESTED``: the caller then keeps LeRobot's stock
    behaviour for ``what``, after one logged warning (per ``what`` and process)."""
    if version_is_tested():
        return False
    if what not in _warned:
        _warned.add(what)
        logger.warning(
            "LeRobot %s is not the tested version %s: %s is off, LeRobot's stock behaviour is used",
            lerobot_version(),
            "/".join(f"{v}x" for v in TESTED),
            what,
        )
    return True


def _private(obj, name: str, owner: str, needed_by: str):
    """``obj.<name>``, a private LeRobot attribute with no stock fallback; a clear error naming what
    needs it if this LeRobot has none."""
    value = getattr(obj, name, None)
    if value is None:
        raise RuntimeError(
            f"LeRobot {lerobot_version()}'s {owner} has no {name} (written for {TESTED}); "
            f"{needed_by} needs an update of lerobot_compat.py"
        )
    return value


def global_conditioning(model, batch: dict[str, Tensor]) -> Tensor:
    """``DiffusionModel._prepare_global_conditioning``: the FiLM conditioning vector (B, cond) of a
    batch of normalised observation histories (B, n_obs_steps, ...). There is no public method that
    returns it; ``generate_actions`` computes it and samples in one go."""
    fn = _private(model, "_prepare_global_conditioning", "DiffusionModel", "batched candidate sampling")
    return fn(batch)


def use_conditioning_method(model_cls: type, method: str) -> None:
    """Make the ``DiffusionModel`` subclass ``model_cls`` compute its FiLM conditioning vector with its
    own ``method(batch)``: LeRobot computes it in ``_prepare_global_conditioning``, which
    ``compute_loss``, ``generate_actions`` and ``global_conditioning`` above call, so training, every
    sampler and every caller of ``global_conditioning`` see the subclass's vector."""

    def prepare(self, batch: dict[str, Tensor]) -> Tensor:
        return getattr(self, method)(batch)

    model_cls._prepare_global_conditioning = prepare


def stock_global_conditioning(model, batch: dict[str, Tensor]) -> Tensor:
    """LeRobot's own ``DiffusionModel._prepare_global_conditioning`` on ``model``, whatever its class
    overrides: [state, environment state] per observation step, flattened to (B, n_obs_steps (S + D))."""
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionModel

    needed_by = "the 'flat' obstacle encoder"
    return _private(DiffusionModel, "_prepare_global_conditioning", "DiffusionModel", needed_by)(model, batch)


def diffusion_unet(config, global_cond_dim: int):
    """LeRobot's conditional 1-D U-Net (``DiffusionConditionalUnet1d``) for a FiLM conditioning vector of
    ``global_cond_dim`` values, compiled as ``DiffusionModel`` compiles its own with ``compile_model``
    (which builds it for the flattened state and environment values)."""
    import torch
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionConditionalUnet1d

    unet = DiffusionConditionalUnet1d(config, global_cond_dim=global_cond_dim)
    if config.compile_model:
        unet = torch.compile(unet, mode=config.compile_mode)
    return unet


def _queues(policy) -> dict:
    needed_by = "the safety layer and the lean inference path"
    return _private(policy, "_queues", "DiffusionPolicy", needed_by)


def push_observation(policy, batch: dict[str, Tensor]) -> None:
    """Append one observation (B, ...) to ``DiffusionPolicy._queues``, the n_obs_steps history that
    ``select_action`` keeps (LeRobot's ``populate_queues``: the first one fills the history)."""
    from lerobot.policies.utils import populate_queues

    policy._queues = populate_queues(_queues(policy), batch)


def queued_history(policy, batch: dict[str, Tensor]) -> dict[str, Tensor]:
    """The keys of ``batch`` as histories (B, n_obs_steps, ...) stacked from the policy's queues, as
    ``DiffusionPolicy.predict_action_chunk`` takes them; ``batch`` itself (an offline batch of
    histories) while the queues are empty."""
    import torch

    queues = _queues(policy)
    if not any(len(q) > 0 for q in queues.values()):
        return batch
    return {k: torch.stack(list(queues[k]), dim=1) for k in batch if k in queues}


def add_weights_loaded_hook(policy_cls: type, hook: Callable) -> None:
    """Run ``hook(model, model_file) -> model`` after LeRobot's ``_load_as_safetensor`` loads a
    ``model.safetensors`` into ``policy_cls`` (and its subclasses): ``from_pretrained`` resolves the
    weights file (local or hub) and hands it to that private classmethod only. On a LeRobot whose
    ``_load_as_safetensor`` is missing or takes other arguments the hook is off (one logged warning)."""
    parent = getattr(super(policy_cls, policy_cls), "_load_as_safetensor", None)
    expected = ["model", "model_file", "map_location", "strict"]
    if parent is None or list(inspect.signature(parent).parameters) != expected:
        if "weights hook" not in _warned:
            _warned.add("weights hook")
            logger.warning(
                "LeRobot %s has no _load_as_safetensor(model, model_file, map_location, strict) (written "
                "for %s): %s loads without its check of the weights file",
                lerobot_version(),
                TESTED,
                policy_cls.__name__,
            )
        return

    def load(cls, model, model_file: str, map_location: str, strict: bool):
        model = super(policy_cls, cls)._load_as_safetensor(model, model_file, map_location, strict)
        return hook(model, model_file)

    policy_cls._load_as_safetensor = classmethod(load)


def denoiser_parts(model):
    """What ``DiffusionModel.conditional_sample`` runs, for a sampler that repeats its loop (for each of
    ``noise_scheduler.timesteps`` after ``set_timesteps(num_inference_steps)``: ``unet(sample, t (B,),
    global_cond)`` then ``noise_scheduler.step``): ``(unet, noise_scheduler, num_inference_steps,
    (horizon, action_dim))``. None on an untested LeRobot (one logged warning): the caller then calls
    ``conditional_sample`` itself."""
    if _untested("the lean inference path (inference_backend 'lean' / 'trace')"):
        return None
    sample_shape = (model.config.horizon, model.config.action_feature.shape[0])
    return model.unet, model.noise_scheduler, model.num_inference_steps, sample_shape


def train_dataloader_worker_kwargs(cfg) -> dict:
    """The DataLoader worker options ``lerobot-train`` passes for a ``TrainPipelineConfig`` (its private
    ``_dataloader_worker_kwargs``: prefetch factor, persistent workers, multiprocessing context)."""
    from lerobot.scripts import lerobot_train

    fn = _private(lerobot_train, "_dataloader_worker_kwargs", "lerobot_train", "the throughput benchmark")
    return fn(cfg)


# -- DatasetReader: fast low-dimensional reads (fast_reads.py) -------------------------------------
_stock_reader: dict[str, Callable] = {}  # LeRobot's own DatasetReader methods while patched


def patch_dataset_reader(get_item: Callable, query_hf_dataset: Callable, getstate: Callable) -> bool:
    """Replace ``DatasetReader.get_item`` and ``_query_hf_dataset`` and give readers ``__getstate__``
    (once; idempotent). Returns whether the patch is active: False on an untested LeRobot."""
    if _untested("fast windowed reads (DatasetReader.get_item)"):
        return False
    from lerobot.datasets.dataset_reader import DatasetReader

    if not _stock_reader:
        _stock_reader["_query_hf_dataset"] = DatasetReader._query_hf_dataset
        DatasetReader._query_hf_dataset = query_hf_dataset
        _stock_reader["get_item"] = DatasetReader.get_item
        DatasetReader.get_item = get_item
        DatasetReader.__getstate__ = getstate
    return True


def reader_meta(reader):
    """``DatasetReader._meta``: the dataset's ``LeRobotDatasetMetadata`` (episodes, tasks, keys)."""
    return reader._meta


def reader_relative_rows(reader):
    """``DatasetReader._absolute_to_relative_idx``: absolute frame index -> row of the reader's table
    when it holds selected episodes only, else None."""
    return reader._absolute_to_relative_idx


def reader_table_is_plain(reader) -> bool:
    """The reader's Hugging Face table is loaded and not an index mapping (``Dataset._indices``: a
    ``select``ed view), so its Arrow rows are its rows."""
    return reader.hf_dataset is not None and reader.hf_dataset._indices is None


def reader_is_low_dim(reader) -> bool:
    """No video, camera, depth feature or image transform, and a plain table: the fast reads apply."""
    meta = reader._meta
    return (
        len(meta.video_keys) == 0
        and len(meta.camera_keys) == 0
        and not reader._image_depth_units
        and reader._image_transforms is None
        and reader_table_is_plain(reader)
    )


def stock_reader_method(name: str) -> Callable:
    """LeRobot's own ``DatasetReader.<name>`` (``get_item`` or ``_query_hf_dataset``), patched or not."""
    if name in _stock_reader:
        return _stock_reader[name]
    from lerobot.datasets.dataset_reader import DatasetReader

    return getattr(DatasetReader, name)


def unpatch_dataset_reader() -> None:
    """Put LeRobot's own ``DatasetReader`` methods back (no-op when not patched)."""
    if _stock_reader:
        from lerobot.datasets.dataset_reader import DatasetReader

        DatasetReader._query_hf_dataset = _stock_reader.pop("_query_hf_dataset")
        DatasetReader.get_item = _stock_reader.pop("get_item")
        del DatasetReader.__getstate__


# -- dataset writer (lerobot_formation/data/lerobot_writer.py) ---------------------------------------------
@contextlib.contextmanager
def skip_noop_image_embedding(features: dict):
    """LeRobot's writer runs ``embed_images`` (a row-by-row ``datasets.map``, ~1 ms per frame) on every
    episode; for a dataset with no image or video feature it changes nothing but costs most of the
    write time. Skip it only in that case; the parquet bytes are the same (tested)."""
    if any(ft["dtype"] in ("image", "video") for ft in features.values()) or _untested(
        "skipping the no-op embed_images"
    ):
        yield
        return
    from lerobot.datasets import dataset_writer

    original = dataset_writer.embed_images
    dataset_writer.embed_images = lambda ds: ds
    try:
        yield
    finally:
        dataset_writer.embed_images = original


def save_episode_buffer(ds, frames: dict[str, np.ndarray], task: str) -> bool:
    """Save one episode of ``frames`` (feature -> (n, ...) array) with ``ds.save_episode(episode_data=...)``
    and a buffer built here in the layout ``add_frame`` builds (LeRobot's internal ``episode_buffer``);
    the frames written are the same. Returns False, writing nothing, on an untested LeRobot: the caller
    then takes the stock ``add_frame`` path."""
    if _untested("pre-built episode buffers (save_episode(episode_data=...))"):
        return False
    from lerobot.utils.constants import ACTION

    n = len(frames[ACTION])
    buf = {
        "size": n,
        "task": [task] * n,
        "episode_index": ds.meta.total_episodes,
        "frame_index": np.arange(n),
        "timestamp": np.arange(n) / ds.meta.fps,  # float64 like add_frame; cast on write
        "index": [],
        "task_index": [],
    }
    buf.update(frames)
    ds.save_episode(episode_data=buf)
    return True


def keep_final_eval_frame(final_frame_key: str) -> bool:
    """Make ``lerobot-eval``'s videos of formation envs end on the frame that shows the outcome.

    LeRobot 0.6.1's ``eval_policy`` renders after the reset and after every step, then writes
    ``frames[: done_index + 1]`` of each episode: the reset frame and the frames *before* the ending
    step, never the frame after it. For a vector env whose metadata has ``final_frame_key``
    (our ``EpisodeOverlay`` sets it) this wraps ``lerobot_eval.rollout`` so that the render after the
    reset is skipped: frame k is then the one after step k and the written slice ends on the ending
    step (the video starts at t = 0.1 s). Other envs keep LeRobot's frames. Patches only a
    ``lerobot_eval`` already imported (every CLI that evaluates has imported it before it imports the
    plugins); returns True if the patch is in place.
    """
    import functools

    module = sys.modules.get("lerobot.scripts.lerobot_eval")
    if module is None or _untested("eval videos ending on the outcome frame"):
        return False
    original = module.rollout
    if getattr(original, "_formation_final_frame", False):
        return True

    @functools.wraps(original)
    def rollout(*args, **kwargs):
        env = kwargs["env"] if "env" in kwargs else args[0]
        render = kwargs.get("render_callback")
        if render is not None and (getattr(env, "metadata", None) or {}).get(final_frame_key):
            seen_reset = []

            def after_first(e, render=render):
                if seen_reset:
                    render(e)
                else:  # the first call is the render after the reset
                    seen_reset.append(True)

            kwargs["render_callback"] = after_first
        return original(*args, **kwargs)

    rollout._formation_final_frame = True  # type: ignore[attr-defined]
    module.rollout = rollout
    return True
