"""Per-episode formation metrics for LeRobot's evaluator (gymnasium + NumPy only, no torch/lerobot).

``lerobot-eval`` keeps only three numbers per episode (``sum_reward``, ``max_reward``, ``success``)
and drops every other ``info`` key, so a plugin cannot add columns to ``eval_info.json``.
``FormationEpisodeMetrics`` wraps one ``FormationEnv`` (under its ``TimeLimit``) and, when an
episode ends:

1. adds ``info["formation_metrics"]``: the SPEC "Metrics" of the episode, recorded and computed by
   the engine's own code (``core.episodes.rollout.frame_record`` / ``step_record``, then
   ``core.episodes.metrics.episode_metrics``), plus ``outcome``, ``steps``,
   ``scene_seed`` (None for a scene without one: from a scenes file or given by hand),
   ``scene_index`` (the scene's index in ``scenes_file``, None for a sampled scene) and
   ``reset_seed``. A vector env carries it in ``info["final_info"]``;
   any Python caller of ``FormationEnvConfig.create_envs`` sees it;
2. if ``log_path`` is set, appends the same record as one JSON line to that file (NaN -> null),
   with ``run_id`` (one per ``create_envs`` call: start time and pid, shared by its sub-envs and
   their worker processes), ``env_index`` (the sub-env), ``episode_index`` (0, 1, ... per sub-env
   within the run), ``wall_time`` and ``pid``, so appends of several runs to one file can be told
   apart. Clearances are null in a scene with no obstacle (``core.episodes.metrics``).
   ``--env.episode_metrics_path=<file>`` turns this on for ``lerobot-eval`` and for the env
   evaluation inside ``lerobot-train``; join the lines with ``eval_info.json``'s
   ``per_task[*].metrics`` / per-episode ``seed`` through ``reset_seed``. Episodes LeRobot
   discards (the surplus of the last batch when ``n_episodes`` is not a multiple of the batch
   size) are logged too; their ``reset_seed`` is past the last seed LeRobot reports.
3. a run never mixes silently with an earlier one: ``start_metrics_file`` (called by
   ``FormationEnvConfig`` at start-up and per ``create_envs``) refuses a file that already holds
   lines unless ``episode_metrics_exists`` is ``"append"`` or ``"overwrite"``; the runs a process
   has started itself (every in-training evaluation of one ``lerobot-train``) append.

Episode metrics key list: ``core.episodes.metrics.METRIC_KEYS``, ``FLAG_KEYS`` (``success``,
``collision``, ``timeout``) and ``struck_by_mover`` (``core.episodes.metrics.mover_strikes``: a moving
obstacle struck a team that was not closing on it), as in the bench's ``results.json``.
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from lerobot_formation.core.episodes.metrics import STRUCK_KEY, episode_metrics, mover_strikes
from lerobot_formation.core.episodes.rollout import (
    COLLISION,
    OUTCOME_NAMES,
    SUCCESS,
    TIMEOUT,
    EpisodeRecords,
    frame_record,
    step_record,
)

INFO_KEY = "formation_metrics"
METRICS_FILE_MODES = ("error", "append", "overwrite")
_STARTED: set[Path] = set()  # metrics files this process has started a run in (it appends to them)


def check_metrics_file(path: str | os.PathLike, mode: str) -> None:
    """Raise ``ValueError`` for an unknown ``mode`` and ``FileExistsError`` if ``mode`` is ``"error"``
    and ``path`` already holds lines that this process did not write."""
    if mode not in METRICS_FILE_MODES:
        raise ValueError(f"env.episode_metrics_exists must be one of {METRICS_FILE_MODES}, got {mode!r}")
    resolved = Path(path).resolve()
    if mode == "error" and resolved not in _STARTED and resolved.is_file() and resolved.stat().st_size:
        with open(resolved, "rb") as f:
            lines = sum(1 for _ in f)
        raise FileExistsError(
            f"episode metrics file {path} already holds {lines} lines of an earlier run; name a new file, "
            "or pass --env.episode_metrics_exists=append to add to it or =overwrite to replace it"
        )


def start_metrics_file(path: str | os.PathLike, mode: str) -> None:
    """Check ``path`` (``check_metrics_file``) once per process and, with ``"overwrite"``, remove the
    earlier run's file; later runs of this process append to it."""
    resolved = Path(path).resolve()
    if resolved in _STARTED:
        return
    check_metrics_file(path, mode)
    if mode == "overwrite" and resolved.is_file():
        resolved.unlink()
    _STARTED.add(resolved)


def new_run_id() -> str:
    """A run id for the JSONL lines: local start time and pid, e.g. ``20261201T120501-4242``, plus 4 random
    hex digits against pid reuse."""
    return f"{time.strftime('%Y%m%dT%H%M%S')}-{os.getpid()}-{os.urandom(2).hex()}"


class FormationEpisodeMetrics(gym.Wrapper):
    """Record one ``FormationEnv`` episode and report its formation metrics when it ends.

    Args:
        env: a ``FormationEnv``, usually under a ``TimeLimit`` (truncation counts as a timeout).
        log_path: JSON-lines file to append one record per finished episode to; None: no file.
        run_id: written on every line (default: ``new_run_id()`` of this wrapper's creation).
        env_index: the sub-env's index in its vector env, written on every line.
    """

    def __init__(
        self,
        env: gym.Env,
        log_path: str | os.PathLike | None = None,
        run_id: str | None = None,
        env_index: int = 0,
    ):
        super().__init__(env)
        self.log_path = Path(log_path) if log_path is not None else None
        self.run_id = run_id or new_run_id()
        self.env_index = int(env_index)
        self.episodes_done = 0
        self._frames: list[dict[str, np.ndarray]] | None = None  # frame_record of steps 0..n
        self._steps: list[dict[str, np.ndarray]] = []  # step_record of steps 1..n
        self._reset_seed: int | None = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        self._reset_seed = None if seed is None else int(seed)
        base = self.env.unwrapped
        self._frames = [frame_record(base.state, base.teams.scenes.obstacles, base.params)]
        self._paths = [base.teams.scenes.obstacles[0, :, :2].copy()]  # moving obstacles move in place
        self._steps = []
        return obs, info

    def step(self, action):
        if self._frames is None:
            raise RuntimeError("call reset() before step()")
        base = self.env.unwrapped
        prev_pose = base.state.pose.copy()
        obs, reward, terminated, truncated, info = self.env.step(action)
        action = base.applied_action  # what ran: under conditions, the delayed, noisy, rate-limited command
        self._steps.append(step_record(prev_pose, base.state, action, base.params))
        self._frames.append(frame_record(base.state, base.teams.scenes.obstacles, base.params))
        self._paths.append(base.teams.scenes.obstacles[0, :, :2].copy())
        if terminated or truncated:
            record = self._finish(info)
            record["episode_index"] = self.episodes_done
            self.episodes_done += 1
            info = {**info, INFO_KEY: record}
            if self.log_path is not None:
                self._write(record)
        return obs, reward, terminated, truncated, info

    # -- helpers ---------------------------------------------------------------------------------
    def _finish(self, info: dict[str, Any]) -> dict[str, Any]:
        if info["is_collision"]:
            outcome = COLLISION
        elif info["is_success"]:
            outcome = SUCCESS
        else:
            outcome = TIMEOUT
        base = self.env.unwrapped
        rec = EpisodeRecords.single(self._frames, self._steps, outcome, base.params.dt)
        metrics = episode_metrics(rec, base.scene.start, base.scene.goal)
        rec.obstacle_paths = np.stack(self._paths)[None]
        scenes = base.teams.scenes
        metrics[STRUCK_KEY] = mover_strikes(rec, scenes.obstacles, scenes.mask, base.params.agent_radius)
        record: dict[str, Any] = {
            "outcome": OUTCOME_NAMES[outcome],
            "steps": len(self._steps),
            "scene_seed": int(info["scene_seed"]) if info["scene_seed"] >= 0 else None,  # None: no seed
            "scene_index": info.get("scene_index"),
            "reset_seed": self._reset_seed,
        }
        for key, value in metrics.items():
            v = value[0]
            record[key] = bool(v) if isinstance(v, np.bool_) else float(v)
        return record

    def _write(self, record: dict[str, Any]) -> None:
        line = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in record.items()}
        line.update(run_id=self.run_id, env_index=self.env_index, wall_time=time.time(), pid=os.getpid())
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        # One write of one short line in append mode: lines from several worker processes do not
        # interleave on a local file system.
        with open(self.log_path, "a") as f:
            f.write(json.dumps(line) + "\n")
