"""LeRobot env config ``formation``: ``--env.type=formation`` builds ``FormationNav-v0`` for lerobot-eval.

``lerobot-eval --env.type=formation`` and ``lerobot-train --env.type=formation --env_eval_freq=N``
get a vector env of ``FormationEnv`` teams. Each sub-env is

    FreezeAfterEpisodeEnd(EpisodeOverlay(FormationEpisodeMetrics(TimeLimit(FormationEnv(**gym_kwargs), episode_length))))

built directly by a picklable factory (no gym registry lookup, so ``AsyncVectorEnv`` workers started
with ``forkserver`` need nothing but the import that unpickling the factory does; that import also
registers the gym id and this config). ``FreezeAfterEpisodeEnd`` is LeRobot's: a sub-env that has
finished stops simulating while the rest of the batch runs on. ``EpisodeOverlay`` (``render.py``) writes the
time and, at the end, the outcome on the rendered frames (the eval videos). ``FormationEpisodeMetrics`` adds the
formation metrics (see ``lerobot_formation.envs.episode_metrics``: ``info["final_info"]
["formation_metrics"]`` and, with ``episode_metrics_path``, one JSON line per episode).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, fields, make_dataclass
from typing import Any, ClassVar

import gymnasium as gym
from gymnasium.vector import AutoresetMode
from gymnasium.wrappers import TimeLimit
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.envs.utils import FreezeAfterEpisodeEnd
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_formation.compat.lerobot_compat import keep_final_eval_frame
from lerobot_formation.compat.run_checks import config_error, install_run_hooks
from lerobot_formation.core.encodings.obstacle_grid import ENCODINGS, environment_state_dim
from lerobot_formation.core.episodes.levels import get_level, level_env_fields
from lerobot_formation.core.perception.conditions import (
    CONDITION_FIELDS,
    CONDITION_TYPES,
    Conditions,
    condition_help,
)
from lerobot_formation.core.perception.observation import STATE_DIM
from lerobot_formation.core.world.presets import SCENE_MIXES, SCENE_PRESETS, SceneConfig
from lerobot_formation.core.world.scene_files import load_scenes
from lerobot_formation.envs.env import FormationEnv
from lerobot_formation.envs.episode_metrics import (
    FormationEpisodeMetrics,
    check_metrics_file,
    new_run_id,
    start_metrics_file,
)
from lerobot_formation.envs.render import FINAL_FRAME_KEY, EpisodeOverlay

ACTION_DIM = 2  # [v, omega]
SCENE_CHOICES = (*SCENE_PRESETS, *SCENE_MIXES)  # what env.scene_preset takes: a preset or a mixture
# The encoding of an env config whose obstacle_encoding nobody gave and no policy handed over: the gym
# env's own default (``FormationEnv``), the paper's grid.
DEFAULT_OBSTACLE_ENCODING = "grid"


def check_policy_features(env_cfg: FormationEnvConfig, policy_cfg) -> None:
    """Raise ``ValueError`` (logged) if the env's ``observation.environment_state`` does not have the
    size of the policy's input (a dataset of one obstacle encoding, an env of another), or has it
    under another encoding than the policy's own (``nearest+route`` and ``nearest+maproute`` have
    the same size and differ in what their route hint plans on)."""
    feature = (getattr(policy_cfg, "input_features", None) or {}).get(OBS_ENV_STATE)
    if feature is None:
        return
    ours = environment_state_dim(env_cfg.encoding)
    theirs = tuple(feature.shape)
    wanted = getattr(policy_cfg, "obstacle_encoding", None)
    if theirs == (ours,):
        if wanted in ENCODINGS and wanted != env_cfg.encoding:
            raise config_error(
                f"--env.obstacle_encoding={env_cfg.encoding} gives '{OBS_ENV_STATE}' the size the "
                f"policy takes, but the policy observes {wanted!r}: pass --env.obstacle_encoding={wanted}"
            )
        return
    sizes = ", ".join(f"{e} {environment_state_dim(e)}" for e in ENCODINGS)
    hint = f"pass --env.obstacle_encoding={wanted}" if wanted else f"the encodings' sizes: {sizes}"
    size = theirs[0] if len(theirs) == 1 else theirs
    raise config_error(
        f"--env.obstacle_encoding={env_cfg.encoding} gives '{OBS_ENV_STATE}' {ours} values, but the "
        f"policy takes {size} (its dataset or checkpoint{f' uses {wanted!r}' if wanted else ''}): {hint}"
    )


def report_level_seed(env_cfg: FormationEnvConfig, eval_seed: int | None) -> str | None:
    """Log (and return) a warning when ``lerobot-eval --env.level=K`` starts from another seed than the
    level's: its episodes then play other scenes of the level's distribution, not the level's."""
    if env_cfg.level is None or eval_seed is None:
        return None
    level = get_level(env_cfg.level)
    if eval_seed == level.seed:
        return None
    line = (
        f"--env.level={env_cfg.level} with --seed={eval_seed}: episode i plays the scene of seed {eval_seed} + i, "
        f"not {level.name}'s scenes (seeds {level.seed:,} + i, the bench's --scenes {level.name}:N); pass "
        f"--seed={level.seed} to evaluate the level"
    )
    logging.getLogger("lerobot_formation").warning(line)
    return line


@dataclass
class FormationEnvFactory:
    """Builds one LeRobot sub-env. A module-level class, so it pickles by reference for worker processes.

    Args:
        env_kwargs: keyword arguments of ``FormationEnv``.
        episode_length: control steps before truncation (``TimeLimit``; LeRobot reads
            ``_max_episode_steps`` from it).
        episode_metrics_path: JSON-lines file for per-episode formation metrics, or None.
        run_id: run id of the JSON lines (one per ``create_envs`` call), None: the wrapper's own.
        env_index: the sub-env's index, written on its JSON lines.
    """

    env_kwargs: dict[str, Any]
    episode_length: int
    episode_metrics_path: str | None = None
    run_id: str | None = None
    env_index: int = 0

    def __call__(self) -> gym.Env:
        env = TimeLimit(FormationEnv(**self.env_kwargs), max_episode_steps=self.episode_length)
        env = FormationEpisodeMetrics(
            env, log_path=self.episode_metrics_path, run_id=self.run_id, env_index=self.env_index
        )
        # Outside the TimeLimit, so a truncation shows as the timeout; inside the freeze, so a finished
        # sub-env keeps rendering its last frame with the outcome.
        return FreezeAfterEpisodeEnd(EpisodeOverlay(env))


# The env config's condition fields, built from ``core.perception.conditions.Conditions`` (where each is declared
# once, with its help and bounds): the same names, types and defaults (all off), and the help that
# draccus shows for ``--env.<field>`` (draccus takes a field's ``metadata["custom_args"]`` as the
# options of its argument). ``FormationEnvConfig`` checks them by building ``Conditions``.
ConditionFields = make_dataclass(
    "ConditionFields",
    [
        (
            f.name,
            CONDITION_TYPES[f.name],
            field(default=f.default, metadata={"custom_args": {"help": condition_help(f.name)}}),
        )
        for f in fields(Conditions)
    ],
    module=__name__,
)
ConditionFields.__doc__ = (
    "The condition fields of ``FormationEnvConfig`` (``core.perception.conditions.Conditions``)."
)


@EnvConfig.register_subclass("formation")
@dataclass
class FormationEnvConfig(ConditionFields, EnvConfig):
    """The formation-navigation env for ``lerobot-eval`` / ``lerobot-train`` (``--env.type=formation``).

    Args:
        task: gym task name; the gym id is ``gym_formation/<task>``.
        fps: control rate [Hz] (dt = 0.1 s); also the video frame rate.
        episode_length: control steps per episode before a timeout (SPEC: 600 = 60 s).
        obstacle_encoding: ``"grid"`` (the paper's 7x7 radius grid + goal, 51 values) or
            ``"grid+list"`` (plus the 5 obstacles [x, y, r], 66 values) or ``"nearest"`` (goal and
            the 12 nearest obstacles in the midpoint's frame, 50 values, any obstacle count) or
            ``"nearest+route"`` (the same plus PAC's cost-to-go route hint from those obstacles, 55
            values) or ``"nearest+maproute"`` (the same 55, the route planned on every obstacle of
            the team's map) or ``"nearest+velocity"`` / ``"nearest+route+velocity"`` (with each observed
            obstacle's velocity, 74 / 79 values). None (default): the run's policy's ``obstacle_encoding``
            (``lerobot-eval`` / ``lerobot-train`` hand the env its policy config at start-up,
            ``take_policy_encoding``), or without one ``DEFAULT_OBSTACLE_ENCODING`` ("grid", the gym
            env's own default); a given value that differs from the policy's is a config error naming
            both. ``encoding`` is the resolved value.
        level: a graded level (``core.episodes.levels``: "0".."5" or "level0".."level5"), or None. When set, the
            level's scene preset and all its conditions apply (``level_env_fields``); ``scene_preset``,
            ``scenes_file`` and the condition fields must then be left at their defaults (or equal the
            level's): any other value is a config error, as in the bench, since a level is a fixed
            benchmark (a field at its default cannot be told from one not given, so it is the level's).
            Episode i of ``lerobot-eval --seed=S`` plays the scene of seed S + i, so ``--seed=1000000``
            (the level's ``seed``) evaluates the bench's ``levelK:N`` scenes.
        scene_preset: scene distribution of seeded resets: a preset (``core.world.presets.SCENE_PRESETS``:
            "paper", "wide", "gates", "blockers", "dense", "goals", "bend", "trap", "crowd", "long",
            "behind") or a mixture (``core.world.presets.SCENE_MIXES``: "structures", "mixed-hard"; seed s
            from preset ``mix[s % k]``, the bench's ``<mix>:N`` scene of seed s).
        scenes_file: JSON scenes file (``core.world.scene_files.save_scenes``); reset seed s picks scene s of the
            file (a seed past its end is an error: run lerobot-eval with ``--seed=0`` and at most as many
            episodes as the file holds). None: the scene of seed s is sampled (``sample_scenes``).
        render_mode: ``"rgb_array"`` (lerobot-eval always renders some episodes to video).
        episode_metrics_path: if set, every finished episode appends its formation metrics (one
            JSON line) to this file; see ``lerobot_formation.envs.episode_metrics``.
        the condition fields (``ConditionFields``: every field of ``core.perception.conditions.Conditions``,
            with its type, default and help, docs/conditions.md): realistic conditions, all off by
            default, e.g. ``--env.sensing_range=3 --env.action_delay=2``; the in-training evaluation
            uses them too.
        episode_metrics_exists: what to do when ``episode_metrics_path`` already holds an earlier
            run's lines: ``"error"`` (refuse at start-up, naming the file), ``"append"`` or
            ``"overwrite"``.
        features: env observation/action features, keyed by the env's own keys; the
            ``environment_state`` shape follows ``obstacle_encoding``.
        features_map: env keys to LeRobot keys (``agent_pos`` -> ``observation.state``,
            ``environment_state`` -> ``observation.environment_state``).
    """

    # Gym task name; the gym id is gym_formation/<task>.
    task: str | None = "FormationNav-v0"
    # Control rate [Hz] (dt = 0.1 s); also the frame rate of the eval videos.
    fps: int = 10
    # Control steps per episode before a timeout (600 = 60 s).
    episode_length: int = 600
    # Obstacle observation: grid (the paper's 7x7 radius grid + goal, 51 values), grid+list (plus the 5
    # obstacles [x, y, r], 66 values), nearest (goal + 12 nearest obstacles in the team's frame, 50
    # values) or nearest+route / nearest+maproute (plus a route hint, 55). None: the run's policy's
    # obstacle_encoding (without a policy: grid, DEFAULT_OBSTACLE_ENCODING); another given one is an error.
    obstacle_encoding: str | None = None
    # A graded level (core/episodes/levels.py: 0..5): its scene preset and conditions, fixed; the condition fields
    # and scene_preset must then stay at their defaults. lerobot-eval --seed=1000000 plays its scenes.
    level: str | None = None
    # Scene distribution of seeded resets: paper, a wider preset (core/world/presets.py SCENE_PRESETS) or a
    # mixture of presets (SCENE_MIXES: structures, mixed-hard).
    scene_preset: str = "paper"
    # JSON scenes file (core.world.scene_files.save_scenes); reset seed s plays scene s of the file (a seed past its
    # end is an error, no wrap-around: use --seed=0). None: the scene of seed s is sampled.
    scenes_file: str | None = None
    # Render mode of the sub-envs; lerobot-eval renders episodes to video with rgb_array.
    render_mode: str = "rgb_array"
    # If set, each finished episode appends its formation metrics as a JSON line to this file.
    episode_metrics_path: str | None = None
    # If episode_metrics_path already holds an earlier run's lines: error (refuse), append or overwrite.
    episode_metrics_exists: str = "error"
    # Parallel tasks of a multi-task benchmark (LeRobot's EnvConfig field; one task here).
    max_parallel_tasks: int = 1
    # Skip gymnasium's env checker when LeRobot makes the env (LeRobot's EnvConfig field).
    disable_env_checker: bool = True
    # Env observation/action features by the env's own keys; the environment_state shape follows
    # obstacle_encoding (set in __post_init__).
    features: dict[str, PolicyFeature] = field(
        default_factory=lambda: {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(ACTION_DIM,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
            "environment_state": PolicyFeature(type=FeatureType.ENV, shape=(environment_state_dim("grid"),)),
        }
    )
    # Env keys to LeRobot keys: agent_pos -> observation.state, environment_state ->
    # observation.environment_state.
    features_map: dict[str, str] = field(
        default_factory=lambda: {
            ACTION: ACTION,
            "agent_pos": OBS_STATE,
            "environment_state": OBS_ENV_STATE,
        }
    )

    # The run's policy config, handed over by lerobot-train's / lerobot-eval's pipeline config once it
    # has resolved it (compat.run_checks.hand_env_its_policy); None elsewhere. Not a config field.
    run_policy: ClassVar[Any] = None
    run_eval_seed: ClassVar[int | None] = None  # lerobot-eval's --seed, handed over like run_policy

    def __post_init__(self) -> None:
        install_run_hooks()  # a formation run: one-line config errors, the training output lock
        if self.obstacle_encoding is not None and self.obstacle_encoding not in ENCODINGS:
            raise config_error(
                f"env.obstacle_encoding must be one of {ENCODINGS}, got {self.obstacle_encoding!r}"
            )
        if self.scene_preset not in SCENE_CHOICES:
            raise config_error(f"env.scene_preset must be one of {SCENE_CHOICES}, got {self.scene_preset!r}")
        if self.episode_length < 1:
            raise config_error(f"env.episode_length must be >= 1, got {self.episode_length}")
        try:
            self._field_conditions()
        except ValueError as e:
            raise config_error(str(e).replace("conditions: ", "env.")) from e
        if self.level is not None:
            self._check_level()
        if self.scenes_file is not None:
            try:  # at start-up, not at the first evaluation
                load_scenes(self.scenes_file, self._scene_config())
            except ValueError as e:
                raise config_error(f"env.scenes_file: {e}") from e
        if self.episode_metrics_path is not None:
            try:  # at start-up: lerobot-train builds its eval envs only at the first evaluation
                check_metrics_file(self.episode_metrics_path, self.episode_metrics_exists)
            except (ValueError, FileExistsError) as e:
                raise config_error(str(e)) from e
        self._set_environment_state_feature()

    @property
    def encoding(self) -> str:
        """The obstacle encoding the env observes: ``obstacle_encoding``, or where none was given and no
        policy handed one over, ``DEFAULT_OBSTACLE_ENCODING``."""
        return self.obstacle_encoding or DEFAULT_OBSTACLE_ENCODING

    def _set_environment_state_feature(self) -> None:
        self.features["environment_state"] = PolicyFeature(
            type=FeatureType.ENV, shape=(environment_state_dim(self.encoding),)
        )

    def take_policy_encoding(self, policy_cfg) -> None:
        """At start-up (``compat.run_checks.hand_env_its_policy``): an env whose ``obstacle_encoding`` was
        not given takes the policy's; a given one that differs is a config error naming both. A policy
        config without an encoding (another policy type) leaves the env as it is."""
        wanted = getattr(policy_cfg, "obstacle_encoding", None)
        if wanted not in ENCODINGS:
            return
        if self.obstacle_encoding is None:
            self.obstacle_encoding = wanted
            self._set_environment_state_feature()
        elif self.obstacle_encoding != wanted:
            raise config_error(
                f"--env.obstacle_encoding={self.obstacle_encoding} differs from the policy's "
                f"obstacle_encoding={wanted}: drop --env.obstacle_encoding (the env then observes the "
                f"policy's) or pass --env.obstacle_encoding={wanted}"
            )

    @property
    def package_name(self) -> str:
        return "lerobot_formation.envs"

    def get_env_processors(self):
        """LeRobot's env processors (identity), after a start-up check: ``lerobot-train`` calls this once
        it has built the policy and before the first training step (``lerobot-eval`` before the first
        episode), so an env whose observation the policy cannot take (``--env.obstacle_encoding``) is
        refused there, not at the first in-training evaluation (``check_policy_features``). The policy
        config is ``run_policy``, which their pipeline configs hand over (``compat.run_checks``); ``lerobot-eval --env.level=K`` with another
        ``--seed`` than the level's (``run_eval_seed``) is a warning (``report_level_seed``)."""
        if self.run_policy is not None:
            check_policy_features(self, self.run_policy)
        report_level_seed(self, self.run_eval_seed)  # lerobot-eval --env.level=K without the level's --seed
        return super().get_env_processors()

    def _check_level(self) -> None:
        """A config error for an unknown ``level``, or a scene or condition field that a level fixes
        given another value than its default and the level's."""
        try:
            level = get_level(self.level)
        except ValueError as e:
            raise config_error(f"env.level: {e}") from e
        defaults = {f.name: f.default for f in fields(self)}
        fixed = {**level_env_fields(self.level), "scenes_file": None}
        clash = [
            f"--env.{name}={getattr(self, name)}"
            for name, value in fixed.items()
            if getattr(self, name) not in (value, defaults[name])
        ]
        if clash:
            raise config_error(
                f"env.level={self.level} fixes the scenes ({fixed['scene_preset']}) and the conditions "
                f"({level.conditions.changed() or 'none'}) of {level.name}; drop {' '.join(clash)}, or drop "
                "--env.level and set the fields yourself"
            )

    def _field_conditions(self) -> Conditions:
        return Conditions(**{name: getattr(self, name) for name in CONDITION_FIELDS})

    def conditions(self) -> Conditions:
        """The realistic conditions (``core.perception.conditions.Conditions``): the level's if ``level`` is set,
        else those of the condition fields."""
        return get_level(self.level).conditions if self.level is not None else self._field_conditions()

    @property
    def effective_scene_preset(self) -> str:
        """The scene preset or mixture that seeded resets draw from: the level's if ``level`` is set."""
        return level_env_fields(self.level)["scene_preset"] if self.level is not None else self.scene_preset

    def _scene_config(self) -> SceneConfig:
        """The ``SceneConfig`` of the env: the preset's; a mixture's scenes are drawn by ``scene_mix``,
        and the default config checks scenes of a file or an option (its checks are every preset's)."""
        return SCENE_PRESETS.get(self.effective_scene_preset, SceneConfig())

    @property
    def gym_id(self) -> str:
        return f"gym_formation/{self.task}"

    @property
    def gym_kwargs(self) -> dict[str, Any]:
        kwargs = {
            "render_mode": self.render_mode,
            "scenes_file": self.scenes_file,
            "obstacle_encoding": self.encoding,
            "scene_config": self._scene_config(),
        }
        if self.effective_scene_preset in SCENE_MIXES:
            kwargs["scene_mix"] = SCENE_MIXES[self.effective_scene_preset]
        conditions = self.conditions()
        if conditions.enabled:
            kwargs["conditions"] = conditions
        return kwargs

    def make_env_factory(self, run_id: str | None = None, env_index: int = 0) -> FormationEnvFactory:
        """The picklable factory of one sub-env (see the module docstring for the wrapper stack)."""
        return FormationEnvFactory(
            env_kwargs=self.gym_kwargs,
            episode_length=self.episode_length,
            episode_metrics_path=self.episode_metrics_path,
            run_id=run_id,
            env_index=env_index,
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
        if self.episode_metrics_path is not None:
            start_metrics_file(self.episode_metrics_path, self.episode_metrics_exists)
        keep_final_eval_frame(FINAL_FRAME_KEY)  # our run: lerobot-eval's videos end on the outcome frame
        run_id = new_run_id()  # one per evaluation run, shared by its sub-envs and worker processes
        fns = [self.make_env_factory(run_id, i) for i in range(n_envs)]
        if use_async_envs and n_envs > 1:
            vec = gym.vector.AsyncVectorEnv(fns, context="forkserver", autoreset_mode=AutoresetMode.SAME_STEP)
        else:
            vec = gym.vector.SyncVectorEnv(fns, autoreset_mode=AutoresetMode.SAME_STEP)
        return {self.type: {0: vec}}
