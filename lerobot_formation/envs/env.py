"""FormationNav-v0: a team of four robots crosses a field of circular obstacles to a goal.

## Description
Two leaders move as a rigid bar; the action plans the velocity of the point midway between them.
Two followers keep a rigid square with the distance-based law of the paper (eq. fol1, with SPEC
erratum 1's sign), integrated with 1 ms sub-steps inside each 0.1 s step (erratum 2). This env is
the follower-controller wrapper: it turns a midpoint plan into four moving robots.

## Action Space
``Box([0, -1.5], [0.6, 1.5], (2,), float32)``: the midpoint's [v (m/s), omega (rad/s)]. Actions
outside the box are clipped; a wrong shape or a NaN/inf raises ``ValueError``.

## Observation Space
A ``Dict`` (LeRobot maps ``agent_pos`` to ``observation.state`` and ``environment_state`` to
``observation.environment_state``):

| key | shape | content |
|---|---|---|
| agent_pos | (7,) | midpoint [x, y, cos phi, sin phi, x', y', omega] |
| environment_state | (51,) "grid" / (66,) "grid+list" / (50,) "nearest" / (55,) "nearest+route" or "nearest+maproute" / (74,) "nearest+velocity" / (79,) "nearest+route+velocity" | see ``core/encodings/obstacle_grid.py``: the paper's 7x7 obstacle-radius grid (49) and goal [x, y] (2), optionally the 5 obstacles [x, y, r]; or ("nearest") the goal and the 12 nearest obstacles [x, y, r, present] in the midpoint's body frame |

## Rewards
Progress toward the goal in metres per step, +1 on success, -1 on collision. (LeRobot reports the
sum; success is what the benchmark counts.)

## Starting State
The paper's start: leaders at (-0.5, 0) and (0.5, 0) facing +y, followers at (-0.2, -0.9) heading
180 deg and (0.4, -1.0) heading 90 deg, or the scene's own start pose.

## Episode End
Terminated on success (midpoint within 0.3 m of the goal) or collision (any agent disc touching any
obstacle). Truncated after 600 steps (60 s) by the ``TimeLimit`` of the registration.

## Scenes
``reset(seed=s)`` gives the scene of seed s (``sample_scenes``; with ``scene_mix``, a mixture of presets
such as ``core.world.presets.SCENE_MIXES["structures"]``, seed s is drawn from preset ``scene_mix[s % k]``,
``sample_mixed``: the bench's ``<mix>:N`` scene of that seed); ``reset(options={"scene": {...}})``
uses a given scene (scenes-file format); with ``scenes_file=...`` seed s is scene s of that file
(0 <= s < number of scenes; a seed past the end raises ``ValueError``, it does not wrap around),
and ``reset()`` without a seed picks one of its scenes at random.

## Errors
``step()`` before ``reset()`` or after the episode terminated (success or collision) raises
``RuntimeError`` (call ``reset()``; LeRobot's ``FreezeAfterEpisodeEnd`` never steps a finished env).
``options`` that is not a dict, a bad scene, a bad action and ``render_size`` outside [8, 2048]
raise ``ValueError``.

## Info
``is_success``, ``is_collision``, ``formation_error``, ``clearance`` (smallest agent gap),
``midpoint_clearance`` (both ``None`` in a scene with no obstacle), ``scene_seed`` (-1 for a scene of a
file or given by hand), ``scene_index`` (the scene's index in ``scenes_file``, else ``None``).

## Realistic conditions
``conditions=Conditions(...)`` (``core.perception.conditions``: sensing range and memory, obstacle and pose
noise, action noise and delay, rate limits, moving obstacles): the observation is then built from what
the team perceives, the action is executed late, noisy and rate limited, and obstacles may move
(``render`` draws them where they are). Off by default: everything as without them.

## Arguments
``gym.make("gym_formation/FormationNav-v0", render_mode="rgb_array", scenes_file=None,
obstacle_encoding="grid", conditions=None, scene_mix=None)``

## Version History
- v0: initial version.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from lerobot_formation.core.encodings.obstacle_grid import environment_state_dim
from lerobot_formation.core.episodes.rollout import SUCCESS, Teams
from lerobot_formation.core.perception.conditions import Conditions
from lerobot_formation.core.perception.observation import STATE_DIM
from lerobot_formation.core.world import dynamics
from lerobot_formation.core.world.dynamics import FormationParams, FormationState
from lerobot_formation.core.world.presets import SceneConfig, scene_preset
from lerobot_formation.core.world.sampling import sample_mixed, sample_scenes
from lerobot_formation.core.world.scene_files import load_scenes, scenes_from_list
from lerobot_formation.core.world.scenes import Scenes
from lerobot_formation.envs.render import Renderer

TASK = "Navigate the four-robot formation to the goal without collisions."


def observation_spaces(obstacle_encoding: str, max_obstacles: int | None = None) -> spaces.Dict:
    d = environment_state_dim(obstacle_encoding, max_obstacles)
    return spaces.Dict(
        {
            "agent_pos": spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float32),
            "environment_state": spaces.Box(-np.inf, np.inf, (d,), np.float32),
        }
    )


def action_space(params: FormationParams) -> spaces.Box:
    """[v, omega] within the bounds the env clips to."""
    return spaces.Box(
        np.array([0.0, -params.omega_max], np.float32),
        np.array([params.v_max, params.omega_max], np.float32),
        dtype=np.float32,
    )


def scene_from_option(scene: Any, config: SceneConfig) -> Scenes:
    if isinstance(scene, Scenes):
        if len(scene) != 1:
            raise ValueError(f"options['scene'] must hold one scene, got {len(scene)}")
        return scene
    if isinstance(scene, dict):
        return scenes_from_list([scene], config)
    raise ValueError(f"options['scene'] must be a dict or Scenes, got {type(scene).__name__}")


def scene_index(seed: int, n_scenes: int, scenes_file=None) -> int:
    """Seed -> scene of a scenes file: seed s is scene s; ValueError past the end (no wrap-around)."""
    seed = int(seed)
    if not 0 <= seed < n_scenes:
        raise ValueError(
            f"seed {seed} is past the end of scenes file {scenes_file or ''} ({n_scenes} scenes, seeds 0..{n_scenes - 1}). "
            "lerobot-eval resets its batches with seeds --seed + i for i < ceil(n_episodes / batch_size) * "
            f"batch_size: pass --seed=0 and an --eval.batch_size that divides --eval.n_episodes <= {n_scenes}"
        )
    return seed


def check_scene_mix(scene_mix) -> tuple[str, ...] | None:
    """``scene_mix`` as a tuple of preset names (None stays None); ValueError naming a bad one."""
    if scene_mix is None:
        return None
    if isinstance(scene_mix, str) or not len(scene_mix):
        raise ValueError(f"scene_mix must be a non-empty sequence of scene preset names, got {scene_mix!r}")
    for name in scene_mix:
        scene_preset(name)
    return tuple(scene_mix)


def seeded_scenes(seeds, config: SceneConfig, scene_mix: tuple[str, ...] | None) -> Scenes:
    """The scenes of seeded resets, (B,) seeds -> Scenes of B: from ``scene_mix`` (seed s from preset
    ``scene_mix[s % k]``, ``sample_mixed``) if given, else from ``config`` (``sample_scenes``)."""
    return sample_mixed(seeds, scene_mix) if scene_mix else sample_scenes(seeds, config)


def _finite_or_none(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


class FormationEnv(gym.Env):
    """Single-team formation navigation, stepped by the engine's ``core.episodes.rollout.Teams`` (one team); see the
    module docstring for the full specification."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        render_mode: str | None = None,
        scenes_file: str | None = None,
        obstacle_encoding: str = "grid",
        params: FormationParams | None = None,
        scene_config: SceneConfig | None = None,
        max_obstacles: int | None = None,
        render_size: int = 256,
        conditions: Conditions | None = None,
        scene_mix: tuple[str, ...] | None = None,
    ):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be one of {self.metadata['render_modes']}, got {render_mode!r}"
            )
        if (
            not isinstance(render_size, int | np.integer)
            or isinstance(render_size, bool)
            or not 8 <= render_size <= 2048
        ):
            raise ValueError(f"render_size must be an int in [8, 2048] pixels, got {render_size!r}")
        self.scenes_file = scenes_file
        self.render_mode = render_mode
        self.params = params or FormationParams()
        self.scene_config = scene_config or SceneConfig()
        self.obstacle_encoding = obstacle_encoding
        self.max_obstacles = max_obstacles
        self.conditions = conditions
        self.scene_mix = check_scene_mix(scene_mix)  # seeded resets draw from it instead of scene_config
        self.scenes = load_scenes(scenes_file, self.scene_config) if scenes_file else None
        self.observation_space = observation_spaces(obstacle_encoding, max_obstacles)
        self.action_space = action_space(self.params)
        self.task = TASK
        self.task_description = TASK
        self._renderer = Renderer(render_size) if render_mode == "rgb_array" else None
        self.scene: Scenes | None = None
        self.scene_index: int | None = None  # index in scenes_file of the current scene
        self.teams: Teams | None = None  # the episode: core.episodes.rollout.Teams of one team
        self._ended: str | None = None  # "success" / "collision" once the episode has terminated
        self.applied_action: np.ndarray | None = None  # (1, 2) the action the last step executed

    @property
    def state(self) -> FormationState | None:
        return self.teams.state if self.teams is not None else None

    # -- gym API ---------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if options is not None and not isinstance(options, dict):
            raise ValueError(f"options must be a dict or None, got {type(options).__name__} {options!r:.80}")
        if seed is not None and self.scenes is not None:
            scene_index(seed, len(self.scenes), self.scenes_file)  # before seeding: a clear ValueError
        super().reset(seed=seed)
        options = options or {}
        self.scene_index = None  # set for a scene of scenes_file; a sampled or given scene has none
        if options.get("scene") is not None:
            self.scene = scene_from_option(options["scene"], self.scene_config)
        elif self.scenes is not None:
            idx = seed if seed is not None else int(self.np_random.integers(len(self.scenes)))
            self.scene_index = scene_index(idx, len(self.scenes), self.scenes_file)
            self.scene = self.scenes[self.scene_index]
        else:
            s = seed if seed is not None else int(self.np_random.integers(0, 2**31 - 1))
            self.scene = seeded_scenes([s], self.scene_config, self.scene_mix)
        self.teams = Teams(
            self.scene, self.params, self.obstacle_encoding, self.max_obstacles, self.conditions
        )
        self._path = [self._positions()]
        self._ended = None
        return self._obs(), self._info(*self.teams.outcome())

    def step(self, action):
        if self.state is None:
            raise RuntimeError("call reset() before step()")
        if self._ended is not None:
            raise RuntimeError(
                f"the episode has ended ({self._ended} at step {int(self.teams.steps[0])}); call reset() before step()"
            )
        a = np.asarray(action)
        if a.shape != (2,):
            raise ValueError(f"action must have shape (2,) [v, omega], got {a.shape}")
        transition = self.teams.step(a[None])
        self.applied_action = transition.action  # (1, 2): the action executed (under conditions: late, noisy)
        self._path.append(self._positions())
        terminated = bool(transition.terminated[0])
        if terminated:
            self._ended = "success" if transition.outcome[0] == SUCCESS else "collision"
        info = self._info(transition.outcome, transition.agent_clearance, transition.midpoint_clearance)
        return self._obs(), float(transition.reward[0]), terminated, False, info

    def render(self):
        if self.render_mode != "rgb_array" or self.scene is None:
            return None
        g = self.params.graph
        return self._renderer.draw(
            self.teams.scenes.obstacles[0],  # where they are now (moving obstacles)
            self.scene.goal[0],
            self._path[-1],
            (g.edge_i, g.edge_j),
            np.asarray(self._path),
            goal_radius=self.params.goal_tolerance,
            agent_radius=self.params.agent_radius,
        )

    # -- helpers ---------------------------------------------------------------------------------
    def _obs(self) -> dict[str, np.ndarray]:
        return {key: value[0] for key, value in self.teams.observe().items()}

    def _positions(self) -> np.ndarray:
        return dynamics.agent_positions(self.teams.state)[0]

    def _info(self, outcome, clear, mid) -> dict[str, Any]:
        info = self.teams.info(outcome, clear, mid)
        return {
            "is_success": bool(info["is_success"][0]),
            "is_collision": bool(info["is_collision"][0]),
            "formation_error": float(info["formation_error"][0]),
            "clearance": _finite_or_none(info["clearance"][0]),  # None: the scene has no obstacle
            "midpoint_clearance": _finite_or_none(info["midpoint_clearance"][0]),
            "scene_seed": int(info["scene_seed"][0]),
            "scene_index": self.scene_index,
        }
