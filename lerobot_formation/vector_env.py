"""FormationVectorEnv: B formation teams stepped by one NumPy call per control step.

Same physics, observations, rewards and termination as ``FormationEnv`` (both call the core's
``dynamics.step``), with gymnasium's vector API and SAME_STEP autoreset: when a team's episode ends,
the returned observation already belongs to its next episode and ``infos["final_obs"]`` /
``infos["final_info"]`` hold the last one. ``reset(seed=s)`` gives env i the scene of seed s + i;
with ``scenes_file``, scene s + i of the file (a seed past its end raises ``ValueError``, as in
``FormationEnv``), and an autoreset picks a scene of the file at random. Info ``clearance`` and
``midpoint_clearance`` are NaN in a scene with no obstacle (``FormationEnv``: None).
"""

from __future__ import annotations

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from lerobot_formation.core import dynamics
from lerobot_formation.core.dynamics import FormationParams
from lerobot_formation.core.obstacle_grid import environment_state, get_encoding
from lerobot_formation.core.rollout import COLLISION, SUCCESS, step_outcome, step_reward
from lerobot_formation.core.scene import FAR, SceneConfig, Scenes, load_scenes, sample_scenes
from lerobot_formation.env import TASK, action_space, midpoint_state, observation_spaces, scene_index


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
    ):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.num_envs = num_envs
        self.params = params or FormationParams()
        self.scene_config = scene_config or SceneConfig()
        self.obstacle_encoding = obstacle_encoding
        self.max_obstacles = max_obstacles
        self.max_episode_steps = max_episode_steps
        self.scenes_file = scenes_file
        self.file_scenes = load_scenes(scenes_file, self.scene_config) if scenes_file else None
        self.single_observation_space = observation_spaces(obstacle_encoding, max_obstacles)
        self.single_action_space = action_space(self.params)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.task = TASK
        M = max(self.scene_config.max_obstacles, 1)
        if self.file_scenes is not None:
            M = max(M, self.file_scenes.obstacles.shape[1])
        self._M = M
        self.scenes: Scenes | None = None
        self.state = None

    def _scenes_for(self, seeds: np.ndarray) -> Scenes:
        if self.file_scenes is not None:
            n = len(self.file_scenes)
            return self.file_scenes[[scene_index(s, n, self.scenes_file) for s in np.asarray(seeds).ravel()]]
        return sample_scenes(seeds, self.scene_config)

    def _load(self, idx: np.ndarray, new: Scenes) -> None:
        """Put scenes ``new`` into env slots ``idx`` and reset their teams."""
        m = new.obstacles.shape[1]
        obs = np.zeros((len(idx), self._M, 3))
        obs[..., :2] = FAR
        obs[:, :m] = new.obstacles
        mask = np.zeros((len(idx), self._M), dtype=bool)
        mask[:, :m] = new.mask
        s = self.scenes
        s.obstacles[idx], s.mask[idx], s.goal[idx], s.start[idx], s.seeds[idx] = (
            obs,
            mask,
            new.goal,
            new.start,
            new.seeds,
        )
        self.state.set(idx, dynamics.initial_state(new.start, self.params))
        self._env_state[idx] = environment_state(
            obs, mask, new.goal, self.obstacle_encoding, self.max_obstacles, pose=self.state.pose[idx]
        )
        self._steps[idx] = 0

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
        if new is None:
            new = self._scenes_for(seeds)
        elif len(new) != B:
            raise ValueError(f"options['scenes'] must hold {B} scenes, got {len(new)}")
        self.scenes = Scenes(
            np.zeros((B, self._M, 3)),
            np.zeros((B, self._M), bool),
            np.zeros((B, 2)),
            np.zeros((B, 3)),
            np.zeros(B, dtype=np.int64),
        )
        self.state = dynamics.initial_state(np.zeros((B, 3)), self.params)
        self._env_state = np.zeros(
            (B, self.single_observation_space["environment_state"].shape[0]), np.float32
        )
        self._steps = np.zeros(B, dtype=np.int64)
        self._load(np.arange(B), new)
        outcome, clear, mid = step_outcome(self.state, self.scenes.obstacles, self.scenes.goal, self.params)
        return self._obs(), self._info(outcome, clear, mid)

    def step(self, actions):
        if self.state is None:
            raise RuntimeError("call reset() before step()")
        a = dynamics.check_action(actions, self.num_envs)
        goal = self.scenes.goal
        prev_pose = self.state.pose
        self.state = dynamics.step(self.state, a, self.params)
        self._steps += 1
        outcome, clear, mid = step_outcome(self.state, self.scenes.obstacles, goal, self.params)
        reward = step_reward(prev_pose, self.state.pose, goal, outcome)
        terminated = (outcome == SUCCESS) | (outcome == COLLISION)
        truncated = (self._steps >= self.max_episode_steps) & ~terminated
        obs = self._obs()
        infos = self._info(outcome, clear, mid)
        done = terminated | truncated
        if done.any():
            idx = np.flatnonzero(done)
            infos["final_obs"] = {k: v.copy() for k, v in obs.items()}
            infos["final_info"] = {k: v.copy() for k, v in infos.items()}
            infos["_final_obs"] = done.copy()
            infos["_final_info"] = done.copy()
            high = len(self.file_scenes) if self.file_scenes is not None else 2**31 - 1
            seeds = self.np_random.integers(0, high, size=len(idx))
            self._load(idx, self._scenes_for(seeds))
            obs = self._obs()
        return obs, reward.astype(np.float64), terminated, truncated, infos

    def _obs(self) -> dict[str, np.ndarray]:
        if get_encoding(self.obstacle_encoding).egocentric:  # the body-frame encoding moves with the team
            s = self.scenes
            self._env_state = environment_state(
                s.obstacles, s.mask, s.goal, self.obstacle_encoding, self.max_obstacles, pose=self.state.pose
            )
        return {"agent_pos": midpoint_state(self.state), "environment_state": self._env_state.copy()}

    def _info(self, outcome, clear, mid) -> dict[str, np.ndarray]:
        pos = dynamics.agent_positions(self.state)
        return {
            "is_success": outcome == SUCCESS,
            "is_collision": outcome == COLLISION,
            "formation_error": dynamics.formation_error(pos, self.params.graph),
            "clearance": np.where(np.isfinite(c := clear.min(axis=1)), c, np.nan),  # NaN: no obstacle
            "midpoint_clearance": np.where(np.isfinite(mid), mid, np.nan),
            "scene_seed": self.scenes.seeds.copy(),
        }
