"""The safety layer with no network: route pursuit's chunk is its proposal, and no checkpoint is read.

``SafetyLayerController`` runs the ``Replanner`` of ``ReplanExperiment(sampled=False)`` (no sampler)
around a ``core.safety.layer.SafetyLayer``: at a replan the candidates are route pursuit's chunk
from the observed route hint and, where it is not safe, the escape manoeuvres, under the same check,
recheck and filter as the learned planner's ("route-pursuit-safe", the baseline of the layer's
rows); with K = 1 and the plan's guidance, route pursuit's chunk moved by the clearance guidance
("route-pursuit-guided", the baseline of guided sampling). It observes as the engine's diffusion
controller does (``core.perception.observation.observe_perception`` with the plan's encoding) and keeps its
plan in the same normalised units, so it acts as that controller with a checkpoint of the same
settings would, bit for bit.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from lerobot_formation.core.perception.conditions import Perception
from lerobot_formation.core.perception.observation import observe_perception
from lerobot_formation.core.safety.layer import SafetySettings
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.policy.replanner import PlanSettings, ReplanExperiment, Replanner, unnormalize_action


def _no_history(rows: torch.Tensor) -> dict:
    return {}  # nothing is sampled: the replanner never reads an observation history


class SafetyLayerController:
    """Batched closed-loop control by the safety layer around route pursuit (module docstring).

    Args:
        safety: the layer's settings (default: the shipped default's, ``SafetySettings()``).
        plan: the plan's settings (default: the shipped checkpoint's, ``PlanSettings()``: chunks of 15
            steps, a replan every 4 steps, K = 10).
        experiment: ablation settings (``ReplanExperiment``; ``sampled`` is always False here).
        params: the formation's parameters.
        name: the controller's name in results.
    """

    def __init__(
        self,
        safety: SafetySettings | None = None,
        plan: PlanSettings | None = None,
        experiment: ReplanExperiment | None = None,
        params: FormationParams | None = None,
        name: str = "route-pursuit-safe",
    ):
        experiment = dataclasses.replace(experiment or ReplanExperiment(), sampled=False)
        self.replanner = Replanner(plan, safety, None, experiment)
        self.params = params or FormationParams()
        self.name = name

    @property
    def stats(self) -> dict[str, int]:
        """The replanner's counts since ``reset`` (``policy.replanner.STAT_KEYS``)."""
        return self.replanner.stats

    def reset(self, view: Perception) -> None:
        self.replanner.reset(len(view))

    def act(self, view: Perception, idx: np.ndarray) -> np.ndarray:
        ps = self.replanner.settings
        env = observe_perception(view, ps.obstacle_encoding, ps.max_obstacles)["environment_state"]
        rows = torch.from_numpy(np.asarray(idx))
        action = self.replanner.act(torch.from_numpy(np.ascontiguousarray(env)), _no_history, rows)
        return unnormalize_action(action).numpy().astype(np.float64)
