"""Processors of ``formation_diffusion``: LeRobot's diffusion processors (found by name by LeRobot).

Pre: rename (none), add batch dim, device, [egocentric obstacles], normalize (STATE and ACTION
MIN_MAX, ENV IDENTITY: see ``FormationDiffusionConfig.normalization_mapping``). Post: unnormalize
the action, move it to the CPU.

The optional ``EgocentricObstaclesProcessorStep`` (``--policy.egocentric_obstacles=true``, needs the
"grid+list" encoding) rewrites the goal and the obstacle list of ``observation.environment_state``
into the midpoint's frame and orders the obstacles nearest surface first. Same size, so the dataset,
the env and the U-Net's conditioning are unchanged; only what the numbers mean is. Why: the planner
must react to obstacles *relative to itself*; in world coordinates a small network has to learn the
subtraction and the rotation by the heading before it can learn to avoid anything.

"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
from lerobot.configs.types import PipelineFeatureType, PolicyFeature
from lerobot.policies.diffusion.processor_diffusion import make_diffusion_pre_post_processors
from lerobot.processor import (
    NormalizerProcessorStep,
    ObservationProcessorStep,
    PolicyAction,
    PolicyProcessorPipeline,
    ProcessorStepRegistry,
)
from lerobot.utils.constants import ACTION
from lerobot.utils.constants import OBS_ENV_STATE as ENV
from lerobot.utils.constants import OBS_STATE as STATE

from lerobot_formation.core.encodings.obstacle_grid import GRID_SIZE, environment_state_dim

if TYPE_CHECKING:  # a type only: the processors need no config module at run time
    from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig


def egocentric_environment_state(state: torch.Tensor, env: torch.Tensor, max_obstacles: int) -> torch.Tensor:
    """World-frame ``environment_state`` (..., 51 + 3M) -> the same layout in the midpoint's frame.

    ``state`` (..., 7) is [x, y, cos phi, sin phi, x', y', omega]. The grid (49) is kept; the goal
    becomes R(phi)^T (g - p); each obstacle row [x, y, r] with r > 0 becomes [R^T (c - p), r] and the
    rows are sorted by surface distance |c - p| - r (padding rows, r = 0, stay zero and last).
    """
    n_grid = GRID_SIZE * GRID_SIZE
    expected = environment_state_dim("grid+list", max_obstacles)
    if env.shape[-1] != expected:
        raise ValueError(
            f"egocentric obstacles need the grid+list encoding ({expected} values), "
            f"got {ENV} with {env.shape[-1]}"
        )
    p, c, s = state[..., 0:2], state[..., 2:3], state[..., 3:4]

    def rotate_into(d: torch.Tensor, c: torch.Tensor, s: torch.Tensor) -> torch.Tensor:  # R(phi)^T d
        return torch.cat([c * d[..., 0:1] + s * d[..., 1:2], -s * d[..., 0:1] + c * d[..., 1:2]], -1)

    goal = rotate_into(env[..., n_grid : n_grid + 2] - p, c, s)
    rows = env[..., n_grid + 2 :].reshape(*env.shape[:-1], max_obstacles, 3)
    centres = rotate_into(rows[..., :2] - p.unsqueeze(-2), c.unsqueeze(-2), s.unsqueeze(-2))
    present = rows[..., 2:3] > 0
    ego = torch.where(present, torch.cat([centres, rows[..., 2:3]], -1), torch.zeros_like(rows))
    surface = torch.where(present[..., 0], ego[..., :2].norm(dim=-1) - ego[..., 2], torch.inf)
    order = surface.argsort(dim=-1, stable=True)
    ego = torch.take_along_dim(ego, order.unsqueeze(-1), dim=-2)
    return torch.cat([env[..., :n_grid], goal, ego.flatten(-2)], -1)


@dataclass
@ProcessorStepRegistry.register(name="formation_egocentric_obstacles")
class EgocentricObstaclesProcessorStep(ObservationProcessorStep):
    """``observation.environment_state``'s goal and obstacle list in the midpoint's frame (see above)."""

    max_obstacles: int = 5

    def observation(self, observation: dict) -> dict:
        if ENV not in observation or STATE not in observation:
            raise ValueError(
                f"egocentric obstacles need {STATE} and {ENV}; the observation has {sorted(observation)}"
            )
        state, env = observation[STATE], observation[ENV]
        if state.shape[:-1] != env.shape[:-1]:
            raise ValueError(f"{STATE} {tuple(state.shape)} and {ENV} {tuple(env.shape)} disagree")
        observation[ENV] = egocentric_environment_state(state.to(env.dtype), env, self.max_obstacles)
        return observation

    def get_config(self) -> dict[str, Any]:
        return {"max_obstacles": self.max_obstacles}

    def transform_features(
        self, features: dict[PipelineFeatureType, dict[str, PolicyFeature]]
    ) -> dict[PipelineFeatureType, dict[str, PolicyFeature]]:
        return features  # same keys, same shapes


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
    if config.fixed_action_bounds and dataset_stats is not None:
        # the env's fixed bounds, so that the policy can unnormalise its own chunks (safety layer)
        action_stats = dict(dataset_stats.get(ACTION, {}))
        action_stats["min"] = torch.tensor(config.action_low, dtype=torch.float32)
        action_stats["max"] = torch.tensor(config.action_high, dtype=torch.float32)
        dataset_stats = {**dataset_stats, ACTION: action_stats}
    pre, post = make_diffusion_pre_post_processors(config, dataset_stats)
    if config.egocentric_obstacles:
        steps = list(pre.steps)
        at = next(i for i, st in enumerate(steps) if isinstance(st, NormalizerProcessorStep))
        steps.insert(at, EgocentricObstaclesProcessorStep(max_obstacles=config.max_obstacles or 5))
        pre.steps = steps
    return pre, post
