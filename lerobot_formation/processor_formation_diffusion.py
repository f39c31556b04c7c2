"""Processors of ``formation_diffusion``: exactly LeRobot's diffusion processors (found by name by LeRobot).

Pre: rename (none), add batch dim, device, normalize (STATE and ACTION MIN_MAX, ENV IDENTITY: see
``FormationDiffusionConfig.normalization_mapping``). Post: unnormalize the action, move it to the CPU.
"""

from __future__ import annotations

from typing import Any

import torch
from lerobot.policies.diffusion.processor_diffusion import make_diffusion_pre_post_processors
from lerobot.processor import PolicyAction, PolicyProcessorPipeline

from lerobot_formation.configuration_formation_diffusion import FormationDiffusionConfig


def make_formation_diffusion_pre_post_processors(
    config: FormationDiffusionConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """LeRobot's ``make_diffusion_pre_post_processors`` for the formation policy.

    Args:
        config: the policy config (features, normalization mapping, device).
        dataset_stats: per-feature statistics for (un)normalization; None when the pipelines are
            loaded from a checkpoint afterwards.

    Returns:
        (preprocessor, postprocessor).
    """
    return make_diffusion_pre_post_processors(config, dataset_stats)
