"""A LeRobot diffusion checkpoint behind the evaluation engine's controller interface.

One batched policy call per replan serves every live episode that needs a new chunk: the episodes'
observation histories (n_obs_steps), normalised by the checkpoint's own preprocessor, go through the
EMA denoiser in one ``generate_actions`` call; the postprocessor unnormalises the chunk, of which
the first ``n_action_steps`` actions are executed open loop, as ``DiffusionPolicy.select_action``
does one episode at a time.

Adaptive sampling draws K candidate chunks per replan in the same batched call and keeps the
safest (``core.footprint.select_safest``: no predicted collision of the whole formation first, then
progress toward the goal). With K = 1 and the same noise it is the standard policy.

The policy's own safety layer (``safety="policy"``: the ``formation_diffusion`` config fields
``num_candidates`` and ``safety_filter``, egocentric "nearest" checkpoints) runs here through the same
functions as in ``select_action`` (``core.safety.select_chunk`` at every replan, ``core.safety.cbf_filter``
on every executed action), on the same observation, so the engine and ``lerobot-eval`` evaluate the
same controller. Replan blending and warm-started replans (``replan_blend_steps``, ``warm_start_step``)
follow ``select_action`` too: each episode keeps its last whole chunk and the actions run since.

It sees only what the teams perceive (``core.conditions.Perception``): the observation is encoded from
the observed pose and obstacles at every step (a world-frame encoding too, since under conditions the
observed obstacles change), and the adaptive rule's cost-to-go is rebuilt for an episode when its
``map_version`` changes, as PAC and MPPI do.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from lerobot_formation.core.conditions import Perception
from lerobot_formation.core.dynamics import FormationParams
from lerobot_formation.core.footprint import select_safest
from lerobot_formation.core.navigation import batch_bounds, cost_to_go, refresh_rows
from lerobot_formation.core.observation import STATE_DIM, observe
from lerobot_formation.core.obstacle_grid import egocentric_encodings, get_encoding
from lerobot_formation.core.replan_blend import blend_replan

logger = logging.getLogger(__name__)


class CheckpointError(ValueError):
    """A policy folder that is not a usable ``formation_diffusion`` checkpoint (the message says why)."""


CHECKPOINT_FILES = (
    "config.json",
    "model.safetensors",
    "policy_preprocessor.json",
    "policy_postprocessor.json",
)


def load_policy(path: str | Path, device: str = "cpu"):
    """Policy and pre/post-processors from a checkpoint folder (``.../pretrained_model`` or a hub-style
    model folder).

    Raises:
        CheckpointError (a ValueError): the folder is missing or incomplete, ``config.json`` is not
            valid JSON or not a ``formation_diffusion`` config (a stock ``diffusion`` checkpoint has no
            obstacle encoding and no EMA), or the weights or processors cannot be loaded (truncated).
    """
    import json

    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    import lerobot_formation.plugin  # noqa: F401  (registers the policy type and its processor step)

    path = Path(path)
    if not path.is_dir():
        raise CheckpointError(f"policy checkpoint folder {path} does not exist")
    missing = [f for f in CHECKPOINT_FILES if not (path / f).is_file()]
    if "config.json" in missing:
        raise CheckpointError(f"{path} is not a policy checkpoint folder: no config.json")
    try:
        raw = json.loads((path / "config.json").read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"{path / 'config.json'} is not valid JSON: {e}") from e
    kind = raw.get("type") if isinstance(raw, dict) else None
    if kind != "formation_diffusion":
        raise CheckpointError(
            f"{path} holds a policy of type {kind!r}, not 'formation_diffusion'; only formation_diffusion "
            "checkpoints can be evaluated here (train one with lerobot-train --policy.type=formation_diffusion)"
        )
    if missing:
        raise CheckpointError(f"{path} is an incomplete checkpoint: no {', '.join(missing)}")
    try:
        cfg = PreTrainedConfig.from_pretrained(path)
    except Exception as e:  # draccus raises many types for a bad field; the message names it
        raise CheckpointError(f"{path / 'config.json'} is not a valid formation_diffusion config: {e}") from e
    cfg.device = device
    try:
        policy = get_policy_class(cfg.type).from_pretrained(path, config=cfg)
    except (OSError, RuntimeError, ValueError, KeyError) as e:
        raise CheckpointError(
            f"{path / 'model.safetensors'} cannot be loaded (truncated, or another model's weights?): "
            f"{type(e).__name__}: {e}"
        ) from e
    except Exception as e:  # safetensors' SafetensorError (truncated file) is no OSError
        if type(e).__name__ != "SafetensorError":
            raise
        raise CheckpointError(f"{path / 'model.safetensors'} cannot be loaded (truncated?): {e}") from e
    policy.eval()
    try:
        pre, post = make_pre_post_processors(
            cfg, pretrained_path=str(path), preprocessor_overrides={"device_processor": {"device": device}}
        )
    except (OSError, ValueError, KeyError, json.JSONDecodeError) as e:
        raise CheckpointError(f"the processors of {path} cannot be loaded: {type(e).__name__}: {e}") from e
    return policy, pre, post


def set_inference_steps(policy, steps: int | None) -> None:
    """Use DDIM with ``steps`` denoising steps (same training betas), or keep the checkpoint's sampler.
    A warm start at or past the last of them (``warm_start_step`` >= steps) is turned off, with a
    warning: it would skip the whole sampler."""
    if steps is None:
        return
    from diffusers.schedulers.scheduling_ddim import DDIMScheduler

    cfg = policy.config
    if not 1 <= steps <= cfg.num_train_timesteps:
        raise ValueError(f"inference steps must be in [1, {cfg.num_train_timesteps}], got {steps}")
    if getattr(cfg, "warm_start_step", 0) >= steps:
        logger.warning(
            "warm_start_step %d needs more than %d inference steps: warm-started replans are off",
            cfg.warm_start_step,
            steps,
        )
        cfg.warm_start_step = 0
    for model in (policy.diffusion, getattr(policy, "ema_diffusion", None)):
        if model is None:
            continue
        model.noise_scheduler = DDIMScheduler(
            num_train_timesteps=cfg.num_train_timesteps,
            beta_start=cfg.beta_start,
            beta_end=cfg.beta_end,
            beta_schedule=cfg.beta_schedule,
            clip_sample=cfg.clip_sample,
            clip_sample_range=cfg.clip_sample_range,
            prediction_type=cfg.prediction_type,
            timestep_spacing=cfg.timestep_spacing,
        )
        model.num_inference_steps = steps


class DiffusionController:
    """Batched closed-loop control with a diffusion checkpoint.

    Args:
        path: checkpoint folder.
        candidates: K candidate chunks per replan.
        adaptive: choose among the candidates with ``select_safest`` (default: K > 1). With K = 1
            and the same noise, the adaptive policy equals the standard one.
        num_inference_steps: DDIM steps (None: the checkpoint's own sampler and step count).
        seed: seeds the torch generator of the initial noise, so runs are repeatable.
        margin: clearance [m] the adaptive rule demands of the rigid-template footprint; followers
            lag their slots by up to ~0.1 m (99th percentile under PAC), which it covers.
    """

    def __init__(
        self,
        path: str | Path,
        candidates: int = 1,
        adaptive: bool | None = None,
        num_inference_steps: int | None = None,
        seed: int = 0,
        params: FormationParams | None = None,
        device: str = "cpu",
        margin: float = 0.1,
        policy_bundle=None,
        safety_filter: str | None = None,
        name: str | None = None,
    ):
        if candidates < 1:
            raise ValueError(f"candidates must be >= 1, got {candidates}")
        self.policy, self.pre, self.post = policy_bundle or load_policy(path, device)
        set_inference_steps(self.policy, num_inference_steps)
        # safety_filter None: the legacy world-frame adaptive rule (or standard); "none"/"cbf": the
        # policy's own safety layer (best-of-K with core.safety.select_chunk, optional CBF filter).
        self.policy_safety = safety_filter is not None
        if self.policy_safety:
            cfg = self.policy.config
            if not (get_encoding(cfg.obstacle_encoding).egocentric and cfg.fixed_action_bounds):
                raise ValueError(
                    "the policy's safety layer needs a checkpoint with obstacle_encoding "
                    f"{' or '.join(map(repr, egocentric_encodings()))} and "
                    f"fixed_action_bounds; {path} has {cfg.obstacle_encoding!r}, {cfg.fixed_action_bounds}"
                )
            self.filter = safety_filter
            self.adaptive = False
        else:
            self.filter = "none"
            self.adaptive = candidates > 1 if adaptive is None else adaptive
            if not self.adaptive and candidates != 1:
                raise ValueError(f"the standard policy draws one candidate, got candidates={candidates}")
        self.name = name or ("diffusion-adaptive" if self.adaptive else "diffusion")
        self.K = candidates
        self.seed = seed
        self.params = params or FormationParams()
        self.margin = margin
        self.device = device
        cfg = self.policy.config
        self.n_obs, self.n_act, self.horizon = cfg.n_obs_steps, cfg.n_action_steps, cfg.horizon
        self.encoding = cfg.obstacle_encoding  # stored in (or found once by) the policy config
        self.max_obstacles = cfg.max_obstacles
        self.egocentric = get_encoding(self.encoding).egocentric
        self.template = np.asarray(self.params.graph.template)
        self.stats = {
            "replans": 0,
            "replans_none_safe": 0,
            "escapes": 0,
            "stops": 0,
            "steps": 0,
            "filter_interventions": 0,
        }

    def reset(self, view: Perception) -> None:
        from lerobot_formation.core.rollout import map_obstacles

        B = len(view)
        self.obstacles = view.obstacles.copy()  # the latest observed obstacles of every episode
        dim = get_encoding(self.encoding).dim(self.max_obstacles)
        self.env_history = np.zeros((B, self.n_obs, dim), np.float32)
        self.history = np.zeros((B, self.n_obs, STATE_DIM), np.float32)
        self.started = np.zeros(B, dtype=bool)
        self.queue = np.zeros((B, self.n_act, 2))
        self.queue_pos = np.full(B, self.n_act)
        self.last_action = np.zeros((B, 2))  # the action executed last (replan blending)
        self.has_last = np.zeros(B, dtype=bool)
        # warm-started replans: each episode's last chunk (normalised, whole) and the actions run since
        self.plans = torch.zeros(B, self.horizon - self.n_obs + 1, 2)
        self.executed = torch.zeros(B, dtype=torch.long)
        self.generator = torch.Generator().manual_seed(self.seed)
        # MPPI's tuned field: walls x3 within 0.9 m (x30 leaves one-cell valleys the square cannot use).
        self.ctg_bounds = batch_bounds(view.goal)
        self.ctg = (
            cost_to_go(map_obstacles(view), view.goal, inflate=0.9, wall_cost=3.0, bounds=self.ctg_bounds)
            if self.adaptive
            else None
        )
        self.version = np.array(view.map_version, copy=True)
        self.replans = 0

    def _noise(self, n: int) -> torch.Tensor:
        return torch.randn((n, self.horizon, 2), generator=self.generator)

    @torch.no_grad()
    def plan(self, idx: np.ndarray, poses: np.ndarray) -> np.ndarray:
        """New action chunks (len(idx), n_action_steps, 2) for episodes idx at observed midpoint
        ``poses`` (len(idx), 3); the adaptive rule checks them against the latest observed obstacles."""
        n, K = len(idx), self.K
        obs = {
            "observation.state": torch.from_numpy(self.history[idx]),
            "observation.environment_state": torch.from_numpy(self.env_history[idx]),
        }
        batch = self.pre(obs)
        cfg = self.policy.config
        warm = None
        if cfg.warm_start_step:  # from the unexecuted rest of each episode's last chunk
            from lerobot_formation.modeling_formation_diffusion import warm_start_guess

            rows = torch.from_numpy(idx)
            guess = warm_start_guess(self.plans[rows], self.executed[rows], self.n_obs, self.horizon)
            warm = (guess, torch.from_numpy(self.has_last[idx]))
        # the whole predicted horizon from the current step, K candidates per episode
        chunks = self.policy.sample_action_chunks(batch, K, noise=self._noise(n * K), warm_start=warm)
        cand = self.post(chunks.reshape(n * K, *chunks.shape[2:])).cpu().numpy().astype(np.float64)
        cand = cand.reshape(n, K, *cand.shape[1:])
        cand = blend_replan(cand, self.last_action[idx], self.has_last[idx], cfg.replan_blend_steps)
        self.replans += 1
        self.stats["replans"] += n
        if self.policy_safety and K > 1:
            chosen, info = self.policy.choose_chunk_raw(
                self.env_history[idx, -1], cand, self.last_action[idx], self.has_last[idx]
            )
            self.stats["replans_none_safe"] += int((~info["any_safe"]).sum())
            self.stats["escapes"] += int(info["escaped"].sum())
            self.stats["stops"] += int(info["stopped"].sum())
            return self._keep(idx, chosen)
        if self.policy_safety or not self.adaptive:
            return self._keep(idx, cand[:, 0])
        choice, _ = select_safest(
            poses,
            cand,
            self.obstacles[idx],
            self.ctg[idx],
            self.template,
            self.params.dt,
            self.params.agent_radius,
            self.margin,
        )
        return cand[np.arange(n), choice, : self.n_act]

    def _keep(self, idx: np.ndarray, chosen: np.ndarray) -> np.ndarray:
        """Remember the kept chunks (len(idx), T, 2) [m/s, rad/s] for warm starts; their first
        n_action_steps actions are what runs."""
        rows = torch.from_numpy(idx)
        self.plans[rows] = self.policy.normalize_action(torch.from_numpy(chosen)).to(self.plans.dtype)
        self.executed[rows] = 0
        return chosen[:, : self.n_act]

    def act(self, view: Perception, idx: np.ndarray) -> np.ndarray:
        from lerobot_formation.core.rollout import map_obstacles

        idx = np.asarray(idx)
        self.obstacles[idx] = view.obstacles
        changed = view.map_version != self.version[idx]
        if changed.any():
            if self.ctg is not None:
                sub = view[changed]
                refresh_rows(
                    self.ctg,
                    idx[changed],
                    map_obstacles(sub),
                    sub.goal,
                    self.ctg_bounds,
                    inflate=0.9,
                    wall_cost=3.0,
                )
            self.version[idx[changed]] = view.map_version[changed]
        seen = observe(  # as the env observes it, from what the teams perceive
            view.pose,
            view.velocity,
            view.obstacles,
            view.mask,
            view.goal,
            self.encoding,
            self.max_obstacles,
            obstacle_velocity=view.obstacle_velocity,
            map_obstacles=view.map_obstacles,
        )
        obs, env = seen["agent_pos"], seen["environment_state"]
        new = ~self.started[idx]
        if new.any():  # first observation fills the history, as LeRobot's populate_queues does
            self.history[idx[new]] = obs[new][:, None]
            self.env_history[idx[new]] = env[new][:, None]
            self.started[idx[new]] = True
        old = idx[~new]
        self.history[old] = np.concatenate([self.history[old, 1:], obs[~new][:, None]], axis=1)
        self.env_history[old] = np.concatenate([self.env_history[old, 1:], env[~new][:, None]], axis=1)
        need = self.queue_pos[idx] >= self.n_act
        if need.any():
            rows = idx[need]
            self.queue[rows] = self.plan(rows, view.pose[need])
            self.queue_pos[rows] = 0
        a = self.queue[idx, self.queue_pos[idx]]
        self.queue_pos[idx] += 1
        self.executed[torch.from_numpy(idx)] += 1
        self.stats["steps"] += len(idx)
        if self.filter == "cbf":
            a, changed = self.policy.filter_action_raw(env, a)
            self.stats["filter_interventions"] += int(changed.sum())
            if self.policy.config.replan_on_intervention:  # as select_action: replan at the next step
                self.queue_pos[idx[changed]] = self.n_act
        self.last_action[idx] = a
        self.has_last[idx] = True
        return a
