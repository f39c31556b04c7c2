"""Shared builders for the LeRobot plugin tests: tiny policy configs and fake batches."""

import torch
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_formation.compat.run_checks import FIELDS_BEFORE
from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig

HORIZON, N_OBS, N_ACT = 16, 2, 8


def formation_features(state_dim=7, env_dim=51, action_dim=2):
    inputs = {
        OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(state_dim,)),
        OBS_ENV_STATE: PolicyFeature(type=FeatureType.ENV, shape=(env_dim,)),
    }
    outputs = {ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(action_dim,))}
    return inputs, outputs


def tiny_config(**overrides) -> FormationDiffusionConfig:
    """A tiny "grid" policy with the sampling and safety fields these tests are written for (the
    standard policy: ``FIELDS_BEFORE``, not the shipped layer's defaults)."""
    inputs, outputs = formation_features()
    kwargs = dict(
        **FIELDS_BEFORE,
        obstacle_encoding="grid",
        device="cpu",
        push_to_hub=False,
        input_features=inputs,
        output_features=outputs,
        horizon=HORIZON,
        n_obs_steps=N_OBS,
        n_action_steps=N_ACT,
        down_dims=(16, 32),
        kernel_size=3,
        n_groups=4,
        diffusion_step_embed_dim=16,
        noise_scheduler_type="DDIM",
        num_inference_steps=4,
    )
    kwargs.update(overrides)
    return FormationDiffusionConfig(**kwargs)


def train_batch(batch_size=4, seed=0, env_dim=51):
    g = torch.Generator().manual_seed(seed)
    return {
        OBS_STATE: torch.randn(batch_size, N_OBS, 7, generator=g),
        OBS_ENV_STATE: torch.rand(batch_size, N_OBS, env_dim, generator=g),
        ACTION: torch.rand(batch_size, HORIZON, 2, generator=g) * 2 - 1,
        "action_is_pad": torch.zeros(batch_size, HORIZON, dtype=torch.bool),
    }


def history_batch(batch_size: int, seed: int = 0) -> dict:
    """Normalised observation histories (B, n_obs_steps, ...), as ``sample_action_chunks`` takes them."""
    g = torch.Generator().manual_seed(seed)
    return {
        OBS_STATE: torch.randn(batch_size, N_OBS, 7, generator=g),
        OBS_ENV_STATE: torch.rand(batch_size, N_OBS, 51, generator=g),
    }


def sampling_noise(n: int, seed: int = 1) -> torch.Tensor:
    """Initial noise (n, horizon, 2) of n samples."""
    return torch.randn(n, HORIZON, 2, generator=torch.Generator().manual_seed(seed))


def obs_batch(batch_size=4, seed=1):
    g = torch.Generator().manual_seed(seed)
    return {
        OBS_STATE: torch.randn(batch_size, 7, generator=g),
        OBS_ENV_STATE: torch.rand(batch_size, 51, generator=g),
    }


def nearest_config(**overrides) -> FormationDiffusionConfig:
    """``tiny_config`` of an egocentric 'nearest' policy with fixed action bounds (the safety layer's)."""
    inputs, outputs = formation_features(env_dim=50)
    kw = dict(
        input_features=inputs, output_features=outputs, obstacle_encoding="nearest", fixed_action_bounds=True
    )
    kw.update(overrides)
    return tiny_config(**kw)


def save_nearest_checkpoint(path, **overrides):
    """A tiny untrained 'nearest' policy saved with its processors, as lerobot-train saves one."""
    from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy
    from lerobot_formation.policy.processor_formation_diffusion import (
        make_formation_diffusion_pre_post_processors,
    )

    torch.manual_seed(0)
    cfg = nearest_config(**overrides)
    policy = FormationDiffusionPolicy(cfg)
    stats = {
        OBS_STATE: {
            "min": torch.tensor([-3.0, -3, -1, -1, -0.6, -0.6, -1.5]),
            "max": torch.tensor([9.0, 9, 1, 1, 0.6, 0.6, 1.5]),
        },
        ACTION: {"min": torch.zeros(2), "max": torch.ones(2)},  # replaced by the fixed bounds
    }
    pre, post = make_formation_diffusion_pre_post_processors(cfg, stats)
    policy.save_pretrained(path)
    pre.save_pretrained(path)
    post.save_pretrained(path)
    return path
