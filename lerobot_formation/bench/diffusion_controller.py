"""A LeRobot diffusion checkpoint behind the evaluation engine's controller interface.

The engine keeps every episode's observation history (n_obs_steps, as LeRobot's queues do) and, at
each step, asks the policy's ``Replanner`` (``policy/replanner.py``, the one ``select_action`` runs)
for the next action of the live episodes: one batched policy call per replan serves every episode
that needs a new chunk, through the checkpoint's own preprocessor; the postprocessor unnormalises the
action. K candidates, the filter and warm starts are the policy config's; a bench controller's K and
filter are an override made with ``dataclasses.replace`` (the config's checks run).

It sees only what the teams perceive (``core.perception.conditions.Perception``): the observation is encoded from
the observed pose and obstacles at every step (a world-frame encoding too, since under conditions the
observed obstacles change), and the safety layer scores chunks against those observed obstacles.

The sampler's initial noise comes from one torch generator per episode (``EpisodeNoise``), seeded from
the run's seed, the controller's name and the episode's scene (``episode_noise_seeds``): an episode's
k-th replan draws the same noise whatever other episodes share its batch, in any order, so a sharded
or differently batched run draws what the whole run draws.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
from pathlib import Path

import numpy as np
import torch
from lerobot.utils.constants import OBS_ENV_STATE, OBS_STATE

from lerobot_formation.core.encodings.obstacle_grid import get_encoding
from lerobot_formation.core.perception.conditions import Perception
from lerobot_formation.core.perception.observation import STATE_DIM, observe_perception
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.policy.checkpoint import load_policy, set_inference_steps
from lerobot_formation.policy.replanner import ReplanExperiment, Replanner, check_observation, policy_sampler

logger = logging.getLogger(__name__)

_U64 = 0xFFFF_FFFF_FFFF_FFFF


def episode_noise_seeds(seed: int, name: str, scene_seeds, goals) -> list[int]:
    """The seed (an int < 2**64) of each episode's noise stream, from the run's ``seed``, the
    controller's ``name`` and the episode's scene: its seed (B,) and goal (B, 2). The goal's exact bits
    tell apart scenes that share a seed (scenes given by hand all have -1, and ``hard:N`` draws each
    preset from the same seeds); mixed by ``numpy.random.SeedSequence``."""
    # a stable hash: Python's own hash of a str changes from process to process
    tag = int.from_bytes(hashlib.sha256(name.encode()).digest()[:8], "little")
    goal_words = np.ascontiguousarray(goals, dtype=np.float64).reshape(len(goals), -1).view(np.uint32)
    out = []
    for scene_seed, words in zip(np.asarray(scene_seeds).tolist(), goal_words.tolist(), strict=True):
        entropy = [int(seed) & _U64, tag, int(scene_seed) & _U64, *words]
        out.append(int(np.random.SeedSequence(entropy).generate_state(1, np.uint64)[0]))
    return out


class EpisodeNoise:
    """Initial noise of the sampler from one torch generator per episode: ``noise(rows, K)`` is
    (len(rows) * K, *shape), K draws of ``shape`` from each episode of ``rows`` (indices into the
    seeds) in turn, as the ``Replanner`` asks for it."""

    def __init__(self, seeds: list[int], shape: tuple[int, ...]):
        self.generators = [torch.Generator().manual_seed(s) for s in seeds]
        self.shape = tuple(shape)

    def __call__(self, rows: torch.Tensor, per_row: int) -> torch.Tensor:
        draws = [torch.randn((per_row, *self.shape), generator=self.generators[i]) for i in rows.tolist()]
        return torch.cat(draws) if draws else torch.zeros((0, *self.shape))


class DiffusionController:
    """Batched closed-loop control with a diffusion checkpoint.

    Args:
        path: checkpoint folder.
        num_inference_steps: DDIM steps (None: the checkpoint's own sampler and step count).
        seed: the run's seed of the initial noise: with the name and the scene it seeds each
            episode's own generator (``episode_noise_seeds``), so runs are repeatable.
        params: the formation's parameters (the observation the policy sees).
        device: torch device of the policy.
        policy_bundle: (policy, preprocessor, postprocessor) already loaded from ``path``.
        overrides: policy config fields this controller runs with (e.g. ``num_candidates``,
            ``safety_filter``), applied with ``dataclasses.replace`` to a copy: the loaded policy's
            config is unchanged, so controllers can share one bundle.
        experiment: ablation settings of the replanner (``ReplanExperiment``).
        name: the controller's name in results (default "diffusion").
    """

    def __init__(
        self,
        path: str | Path,
        num_inference_steps: int | None = None,
        seed: int = 0,
        params: FormationParams | None = None,
        device: str = "cpu",
        policy_bundle=None,
        overrides: dict | None = None,
        experiment: ReplanExperiment | None = None,
        name: str = "diffusion",
    ):
        self.policy, self.pre, self.post = policy_bundle or load_policy(path, device)
        set_inference_steps(self.policy, num_inference_steps)
        self.config = dataclasses.replace(self.policy.config, **(overrides or {}))
        self.replanner = Replanner.from_config(self.config, policy_sampler(self.policy), experiment)
        self.name = name
        self.seed = seed
        self.params = params or FormationParams()
        self.device = device
        cfg = self.config
        self.n_obs, self.horizon = cfg.n_obs_steps, cfg.horizon
        self.encoding = cfg.obstacle_encoding
        self.max_obstacles = cfg.max_obstacles

    @property
    def stats(self) -> dict[str, int]:
        """The replanner's counts since ``reset`` (``policy.replanner.STAT_KEYS``)."""
        return self.replanner.stats

    def reset(self, view: Perception) -> None:
        B = len(view)
        dim = get_encoding(self.encoding).dim(self.max_obstacles)
        self.env_history = np.zeros((B, self.n_obs, dim), np.float32)
        self.history = np.zeros((B, self.n_obs, STATE_DIM), np.float32)
        self.started = np.zeros(B, dtype=bool)
        scene_seeds = np.full(B, -1) if view.scene_seed is None else view.scene_seed
        seeds = episode_noise_seeds(self.seed, self.name, scene_seeds, view.goal)
        self.noise = EpisodeNoise(seeds, (self.horizon, 2))
        self.replanner.reset(B)

    def _noise(self, rows: torch.Tensor, per_row: int) -> torch.Tensor:
        return self.noise(rows, per_row)

    def _history(self, rows: torch.Tensor) -> dict[str, torch.Tensor]:
        """Normalised observation histories (len(rows), n_obs_steps, ...) of episodes ``rows``."""
        idx = rows.numpy()
        obs = {
            OBS_STATE: torch.from_numpy(self.history[idx]),
            OBS_ENV_STATE: torch.from_numpy(self.env_history[idx]),
        }
        batch = self.pre(obs)
        check_observation(batch, self.config.input_features, batch[OBS_STATE].dtype)
        return batch

    def act(self, view: Perception, idx: np.ndarray) -> np.ndarray:
        idx = np.asarray(idx)
        seen = observe_perception(view, self.encoding, self.max_obstacles)  # as the env observes it
        obs, env = seen["agent_pos"], seen["environment_state"]
        new = ~self.started[idx]
        if new.any():  # first observation fills the history, as LeRobot's populate_queues does
            self.history[idx[new]] = obs[new][:, None]
            self.env_history[idx[new]] = env[new][:, None]
            self.started[idx[new]] = True
        old = idx[~new]
        self.history[old] = np.concatenate([self.history[old, 1:], obs[~new][:, None]], axis=1)
        self.env_history[old] = np.concatenate([self.env_history[old, 1:], env[~new][:, None]], axis=1)
        action = self.replanner.act(
            torch.from_numpy(np.ascontiguousarray(env)), self._history, torch.from_numpy(idx), self._noise
        )
        return self.post(action).cpu().numpy().astype(np.float64)
