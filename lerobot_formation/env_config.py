"""LeRobot env config ``formation``: ``--env.type=formation`` builds ``FormationNav-v0`` for lerobot-eval.

``lerobot-eval --env.type=formation`` and ``lerobot-train --env.type=formation --env_eval_freq=N``
get a vector env of ``FormationEnv`` teams. Each sub-env is

    FreezeAfterEpisodeEnd(FormationEpisodeMetrics(TimeLimit(FormationEnv(**gym_kwargs), episode_length)))

built directly by a picklable factory (no gym registry lookup, so ``AsyncVectorEnv`` workers started
with ``forkserver`` need nothing but the import that unpickling the factory does; that import also
registers the gym id and this config). ``FreezeAfterEpisodeEnd`` is LeRobot's: a sub-env that has
finished stops simulating while the rest of the batch runs on. ``FormationEpisodeMetrics`` adds the
formation metrics (see ``lerobot_formation.episode_metrics``: ``info["final_info"]
["formation_metrics"]`` and, with ``episode_metrics_path``, one JSON line per episode).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
from gymnasium.vector import AutoresetMode
from gymnasium.wrappers import TimeLimit
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.envs.utils import FreezeAfterEpisodeEnd
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_formation.configuration_formation_diffusion import config_error
from lerobot_formation.core.obstacle_grid import ENCODINGS, environment_state_dim
from lerobot_formation.env import STATE_DIM, FormationEnv
from lerobot_formation.episode_metrics import FormationEpisodeMetrics

ACTION_DIM = 2  # [v, omega]


@dataclass
class FormationEnvFactory:
    """Builds one LeRobot sub-env. A module-level class, so it pickles by reference for worker processes.

    Args:
        env_kwargs: keyword arguments of ``FormationEnv``.
        episode_length: control steps before truncation (``TimeLimit``; LeRobot reads
            ``_max_episode_steps`` from it).
        episode_metrics_path: JSON-lines file for per-episode formation metrics, or None.
    """

    env_kwargs: dict[str, Any]
    episode_length: int
    episode_metrics_path: str | None = None

    def __call__(self) -> gym.Env:
        env = TimeLimit(FormationEnv(**self.env_kwargs), max_episode_steps=self.episode_length)
        env = FormationEpisodeMetrics(env, log_path=self.episode_metrics_path)
        return FreezeAfterEpisodeEnd(env)


@EnvConfig.register_subclass("formation")
@dataclass
class FormationEnvConfig(EnvConfig):
    """The formation-navigation env for ``lerobot-eval`` / ``lerobot-train`` (``--env.type=formation``).

    Args:
        task: gym task name; the gym id is ``gym_formation/<task>``.
        fps: control rate [Hz] (dt = 0.1 s); also the video frame rate.
        episode_length: control steps per episode before a timeout (SPEC: 600 = 60 s).
        obstacle_encoding: ``"grid"`` (the paper's 7x7 radius grid + goal, 51 values) or
            ``"grid+list"`` (plus the 5 obstacles [x, y, r], 66 values). Must match the policy's
            ``observation.environment_state`` shape.
        scenes_file: JSON scenes file (``core.scene.save_scenes``); reset seed s picks scene
            s mod len(file). None: the scene of seed s is sampled (``sample_scenes``).
        render_mode: ``"rgb_array"`` (lerobot-eval always renders some episodes to video).
        episode_metrics_path: if set, every finished episode appends its formation metrics as a
            JSON line to this file (see ``lerobot_formation.episode_metrics``).
        features: env observation/action features, keyed by the env's own keys; the
            ``environment_state`` shape follows ``obstacle_encoding``.
        features_map: env keys to LeRobot keys (``agent_pos`` -> ``observation.state``,
            ``environment_state`` -> ``observation.environment_state``).
    """

    task: str | None = "FormationNav-v0"
    fps: int = 10
    episode_length: int = 600
    obstacle_encoding: str = "grid"
    scenes_file: str | None = None
    render_mode: str = "rgb_array"
    episode_metrics_path: str | None = None
    features: dict[str, PolicyFeature] = field(
        default_factory=lambda: {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(ACTION_DIM,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
            "environment_state": PolicyFeature(type=FeatureType.ENV, shape=(environment_state_dim("grid"),)),
        }
    )
    features_map: dict[str, str] = field(
        default_factory=lambda: {
            ACTION: ACTION,
            "agent_pos": OBS_STATE,
            "environment_state": OBS_ENV_STATE,
        }
    )

    def __post_init__(self) -> None:
        if self.obstacle_encoding not in ENCODINGS:
            raise config_error(
                f"env.obstacle_encoding must be one of {ENCODINGS}, got {self.obstacle_encoding!r}"
            )
        if self.episode_length < 1:
            raise config_error(f"env.episode_length must be >= 1, got {self.episode_length}")
        self.features["environment_state"] = PolicyFeature(
            type=FeatureType.ENV, shape=(environment_state_dim(self.obstacle_encoding),)
        )

    @property
    def package_name(self) -> str:
        return "lerobot_formation"

    @property
    def gym_id(self) -> str:
        return f"gym_formation/{self.task}"

    @property
    def gym_kwargs(self) -> dict[str, Any]:
        return {
            "render_mode": self.render_mode,
            "scenes_file": self.scenes_file,
            "obstacle_encoding": self.obstacle_encoding,
        }

    def make_env_factory(self) -> FormationEnvFactory:
        """The picklable factory of one sub-env (see the module docstring for the wrapper stack)."""
        return FormationEnvFactory(
            env_kwargs=self.gym_kwargs,
            episode_length=self.episode_length,
            episode_metrics_path=self.episode_metrics_path,
        )

    def create_envs(
        self, n_envs: int, use_async_envs: bool = False
    ) -> dict[str, dict[int, gym.vector.VectorEnv]]:
        """``{"formation": {0: VectorEnv}}`` of ``n_envs`` teams, SAME_STEP autoreset as LeRobot's default.

        ``AsyncVectorEnv`` (``forkserver`` workers) if ``use_async_envs`` and ``n_envs > 1``, else
        ``SyncVectorEnv``.
        """
        if n_envs < 1:
            raise ValueError(f"n_envs must be >= 1, got {n_envs}")
        fns = [self.make_env_factory() for _ in range(n_envs)]
        if use_async_envs and n_envs > 1:
            vec = gym.vector.AsyncVectorEnv(fns, context="forkserver", autoreset_mode=AutoresetMode.SAME_STEP)
        else:
            vec = gym.vector.SyncVectorEnv(fns, autoreset_mode=AutoresetMode.SAME_STEP)
        return {self.type: {0: vec}}
