"""FormationVectorEnv: B formation teams stepped by one NumPy call per control step.

A gymnasium face over the engine's batched episodes (``core.episodes.rollout.Teams``, which ``FormationEnv``
steps too): the same physics, observations, rewards and termination, with gymnasium's vector API and SAME_STEP autoreset: when a team's episode ends,
the returned observation already belongs to its next episode and ``infos["final_obs"]`` /
``infos["final_info"]`` hold the last one. ``reset(seed=s)`` gives env i the scene of seed s + i
(with ``scene_mix``, drawn from preset ``scene_mix[(s + i) % k]``, as ``FormationEnv``);
with ``scenes_file``, scene s + i of the file (a seed past its end raises ``ValueError``, as in
``FormationEnv``), and an autoreset picks a scene of the file at random. Info ``clearance`` and
``midpoint_clearance`` are NaN in a scene with no obstacle, ``scene_index`` (the scene's index in
``scenes_file``) NaN for a sampled or given scene (``FormationEnv``: None for both).
"""

from __future__ import annotations

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from lerobot_formation.core.episodes.rollout import Teams
from lerobot_formation.core.perception.conditions import Conditions
from lerobot_formation.core.world.dynamics import FormationParams, FormationState
from lerobot_formation.core.world.presets import SceneConfig, mix_max_obstacles
from lerobot_formation.core.world.scene_files import load_scenes
from lerobot_formation.core.world.scenes import Scenes
from lerobot_formation.envs.env import (
    TASK,
    action_space,
    check_scene_mix,
    observation_spaces,
    scene_index,
    seeded_scenes,
)


class FormationVectorEnv(VectorEnv):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 10, "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(
        self,
        num_envs: int,
        scenes_file: str | None = None,
        obstacle_encoding: str = "grid",
        params: FormationParams | None = None,
        scene_config: SceneConfig | None = None,
        max_obstacles: int | None = None,
        max_episode_steps: int = 600,
        conditions: Conditions | None = None,
        scene_mix: tuple[str, ...] | None = None,
    ):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.num_envs = num_envs
        self.params = params or FormationParams()
        self.scene_config = scene_config or SceneConfig()
        self.obstacle_encoding = obstacle_encoding
        self.max_obstacles = max_obstacles
        self.max_episode_steps = max_episode_steps
        self.conditions = conditions
        self.scene_mix = check_scene_mix(scene_mix)  # seeded resets draw from it instead of scene_config
        self.scenes_file = scenes_file
        self.file_scenes = load_scenes(scenes_file, self.scene_config) if scenes_file else None
        self.single_observation_space = observation_spaces(obstacle_encoding, max_obstacles)
        self.single_action_space = action_space(self.params)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.task = TASK
        M = max(mix_max_obstacles(self.scene_mix) if self.scene_mix else self.scene_config.max_obstacles, 1)
        if self.file_scenes is not None:
            M = max(M, self.file_scenes.obstacles.shape[1])
        self._M = M
        self.teams: Teams | None = None

    @property
    def state(self) -> FormationState | None:
        return self.teams.state if self.teams is not None else None

    @property
    def scenes(self) -> Scenes | None:
        return self.teams.scenes if self.teams is not None else None

    @property
    def _steps(self) -> np.ndarray:
        return self.teams.steps

    def _scenes_for(self, seeds: np.ndarray) -> tuple[Scenes, np.ndarray]:
        """The scenes of ``seeds`` and their indices in ``scenes_file`` (NaN: sampled, no file)."""
        if self.file_scenes is not None:
            n = len(self.file_scenes)
            idx = [scene_index(s, n, self.scenes_file) for s in np.asarray(seeds).ravel()]
            return self.file_scenes[idx], np.asarray(idx, dtype=np.float64)
        scenes = seeded_scenes(seeds, self.scene_config, self.scene_mix)
        return scenes, np.full(len(np.atleast_1d(seeds)), np.nan)

    def reset(self, *, seed=None, options: dict | None = None):
        B = self.num_envs
        super().reset(
            seed=seed if seed is None or isinstance(seed, int) else int(np.asarray(seed).ravel()[0])
        )
        if isinstance(seed, int):
            seeds = seed + np.arange(B)
        elif seed is not None:
            seeds = np.asarray(seed, dtype=np.int64)
            if seeds.shape != (B,):
                raise ValueError(f"seed must be an int or {B} ints, got shape {seeds.shape}")
        else:
            seeds = self.np_random.integers(
                0, len(self.file_scenes) if self.file_scenes is not None else 2**31 - 1, size=B
            )
        options = options or {}
        new = options.get("scenes")
        # The scene's index in scenes_file, as FormationEnv's info["scene_index"] (NaN for its None).
        self._scene_index = np.full(B, np.nan)
        if new is None:
            new, self._scene_index = self._scenes_for(seeds)
        elif len(new) != B:
            raise ValueError(f"options['scenes'] must hold {B} scenes, got {len(new)}")
        self.teams = Teams(
            new.padded(self._M), self.params, self.obstacle_encoding, self.max_obstacles, self.conditions
        )
        return self.teams.observe(), self._info(*self.teams.outcome())

    def step(self, actions):
        if self.teams is None:
            raise RuntimeError("call reset() before step()")
        transition = self.teams.step(actions)
        terminated = transition.terminated
        truncated = self.teams.truncated(transition, self.max_episode_steps)
        obs = self.teams.observe()
        infos = self._info(transition.outcome, transition.agent_clearance, transition.midpoint_clearance)
        done = terminated | truncated
        if done.any():
            idx = np.flatnonzero(done)
            infos["final_obs"] = {k: v.copy() for k, v in obs.items()}
            infos["final_info"] = {k: v.copy() for k, v in infos.items()}
            infos["_final_obs"] = done.copy()
            infos["_final_info"] = done.copy()
            high = len(self.file_scenes) if self.file_scenes is not None else 2**31 - 1
            seeds = self.np_random.integers(0, high, size=len(idx))
            scenes, self._scene_index[idx] = self._scenes_for(seeds)
            self.teams.load(idx, scenes)
            obs = self.teams.observe()
        return obs, transition.reward.astype(np.float64), terminated, truncated, infos

    def _info(self, outcome, clear, mid) -> dict[str, np.ndarray]:
        info = self.teams.info(outcome, clear, mid)
        for key in ("clearance", "midpoint_clearance"):  # NaN: the scene has no obstacle
            info[key] = np.where(np.isfinite(info[key]), info[key], np.nan)
        info["scene_index"] = self._scene_index.copy()
        return info
