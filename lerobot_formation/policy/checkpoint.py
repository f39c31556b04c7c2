"""Loading a ``formation_diffusion`` checkpoint folder (policy and processors), and the DDIM step
override the engine and the benchmarks use."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

logger = logging.getLogger(__name__)


class CheckpointError(ValueError):
    """A policy folder that is not a usable ``formation_diffusion`` checkpoint (the message says why)."""


CHECKPOINT_FILES = (
    "config.json",
    "model.safetensors",
    "policy_preprocessor.json",
    "policy_postprocessor.json",
)


def load_policy(path: str | Path, device: str = "cpu"):
    """Policy and pre/post-processors from a checkpoint folder (``.../pretrained_model`` or a hub-style
    model folder).

    Raises:
        CheckpointError (a ValueError): the folder is missing or incomplete, ``config.json`` is not
            valid JSON or not a ``formation_diffusion`` config (a stock ``diffusion`` checkpoint has no
            obstacle encoding and no EMA), a processor pipeline names a step that is not registered
            with LeRobot (``checkpoint_files``; refused before anything is imported), or the weights
            or processors cannot be loaded (truncated).
    """
    import json

    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    import lerobot_formation.policy.configuration_formation_diffusion  # noqa: F401  (registers the type)
    import lerobot_formation.policy.processor_formation_diffusion  # noqa: F401  (registers its step)
    from lerobot_formation.policy.checkpoint_files import check_processor_configs

    path = Path(path)
    if not path.is_dir():
        raise CheckpointError(f"policy checkpoint folder {path} does not exist")
    missing = [f for f in CHECKPOINT_FILES if not (path / f).is_file()]
    if "config.json" in missing:
        raise CheckpointError(f"{path} is not a policy checkpoint folder: no config.json")
    try:
        raw = json.loads((path / "config.json").read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"{path / 'config.json'} is not valid JSON: {e}") from e
    kind = raw.get("type") if isinstance(raw, dict) else None
    if kind != "formation_diffusion":
        raise CheckpointError(
            f"{path} holds a policy of type {kind!r}, not 'formation_diffusion'; only formation_diffusion "
            "checkpoints can be evaluated here (train one with lerobot-train --policy.type=formation_diffusion)"
        )
    if missing:
        raise CheckpointError(f"{path} is an incomplete checkpoint: no {', '.join(missing)}")
    try:
        cfg = dataclasses.replace(PreTrainedConfig.from_pretrained(path), device=device)
    except Exception as e:  # draccus raises many types for a bad field; the message names it
        from lerobot_formation.compat.run_checks import config_error_in_chain

        why = config_error_in_chain(e) or e  # draccus wraps our checks' one-line errors
        raise CheckpointError(
            f"{path / 'config.json'} is not a valid formation_diffusion config: {why}"
        ) from e
    try:
        check_processor_configs(path)  # before anything names a class to import
    except ValueError as e:
        raise CheckpointError(str(e)) from e
    try:
        policy = get_policy_class(cfg.type).from_pretrained(path, config=cfg)
    except (OSError, RuntimeError, ValueError, KeyError) as e:
        raise CheckpointError(
            f"{path / 'model.safetensors'} cannot be loaded (truncated, or another model's weights?): "
            f"{type(e).__name__}: {e}"
        ) from e
    except Exception as e:  # safetensors' SafetensorError (truncated file) is no OSError
        if type(e).__name__ != "SafetensorError":
            raise
        raise CheckpointError(f"{path / 'model.safetensors'} cannot be loaded (truncated?): {e}") from e
    policy.eval()
    try:
        pre, post = make_pre_post_processors(
            cfg, pretrained_path=str(path), preprocessor_overrides={"device_processor": {"device": device}}
        )
    except (OSError, ValueError, KeyError, json.JSONDecodeError) as e:
        raise CheckpointError(f"the processors of {path} cannot be loaded: {type(e).__name__}: {e}") from e
    return policy, pre, post


def set_inference_steps(policy, steps: int | None) -> None:
    """Use DDIM with ``steps`` denoising steps (same training betas), or keep the checkpoint's sampler.
    A warm start at or past the last of them (``warm_start_step`` >= steps) is turned off, with a
    warning (the policy gets a config copy with ``warm_start_step`` 0): it would skip the whole
    sampler."""
    if steps is None:
        return
    from diffusers.schedulers.scheduling_ddim import DDIMScheduler

    cfg = policy.config
    if not 1 <= steps <= cfg.num_train_timesteps:
        raise ValueError(f"inference steps must be in [1, {cfg.num_train_timesteps}], got {steps}")
    if cfg.warm_start_step >= steps:
        logger.warning(
            "warm_start_step %d needs more than %d inference steps: warm-started replans are off",
            cfg.warm_start_step,
            steps,
        )
        policy.reconfigure(warm_start_step=0)
    for model in (policy.diffusion, getattr(policy, "ema_diffusion", None)):
        if model is None:
            continue
        model.noise_scheduler = DDIMScheduler(
            num_train_timesteps=cfg.num_train_timesteps,
            beta_start=cfg.beta_start,
            beta_end=cfg.beta_end,
            beta_schedule=cfg.beta_schedule,
            clip_sample=cfg.clip_sample,
            clip_sample_range=cfg.clip_sample_range,
            prediction_type=cfg.prediction_type,
        )
        model.num_inference_steps = steps
