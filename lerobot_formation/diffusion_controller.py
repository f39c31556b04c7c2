"""A LeRobot diffusion checkpoint behind the evaluation engine's controller interface.

One batched policy call per replan serves every live episode that needs a new chunk: the episodes'
observation histories (n_obs_steps), normalised by the checkpoint's own preprocessor, go through the
EMA denoiser in one ``generate_actions`` call; the postprocessor unnormalises the chunk, of which
the first ``n_action_steps`` actions are executed open loop, as ``DiffusionPolicy.select_action``
does one episode at a time.

Adaptive sampling draws K candidate chunks per replan in the same batched call and keeps the
safest (``core.footprint.select_safest``: no predicted collision of the whole formation first, then
progress toward the goal). With K = 1 and the same noise it is the standard policy.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from lerobot_formation.core.dynamics import FormationParams, FormationState
from lerobot_formation.core.footprint import select_safest
from lerobot_formation.core.navigation import cost_to_go
from lerobot_formation.core.obstacle_grid import ENCODINGS, environment_state, environment_state_dim
from lerobot_formation.core.scene import Scenes
from lerobot_formation.env import midpoint_state


def load_policy(path: str | Path, device: str = "cpu"):
    """Policy and pre/post-processors from a checkpoint folder (``.../pretrained_model`` or a hub-style
    model folder)."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    import lerobot_formation.plugin  # noqa: F401  (registers the policy type and its processor step)

    path = Path(path)
    if not (path / "config.json").is_file():
        raise FileNotFoundError(f"{path} is not a policy checkpoint folder: no config.json")
    cfg = PreTrainedConfig.from_pretrained(path)
    cfg.device = device
    policy = get_policy_class(cfg.type).from_pretrained(path, config=cfg)
    policy.eval()
    pre, post = make_pre_post_processors(
        cfg, pretrained_path=str(path), preprocessor_overrides={"device_processor": {"device": device}}
    )
    return policy, pre, post


def set_inference_steps(policy, steps: int | None) -> None:
    """Use DDIM with ``steps`` denoising steps (same training betas), or keep the checkpoint's sampler."""
    if steps is None:
        return
    from diffusers.schedulers.scheduling_ddim import DDIMScheduler

    cfg = policy.config
    if not 1 <= steps <= cfg.num_train_timesteps:
        raise ValueError(f"inference steps must be in [1, {cfg.num_train_timesteps}], got {steps}")
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
    ):
        if candidates < 1:
            raise ValueError(f"candidates must be >= 1, got {candidates}")
        self.policy, self.pre, self.post = policy_bundle or load_policy(path, device)
        set_inference_steps(self.policy, num_inference_steps)
        self.adaptive = candidates > 1 if adaptive is None else adaptive
        if not self.adaptive and candidates != 1:
            raise ValueError(f"the standard policy draws one candidate, got candidates={candidates}")
        self.name = "diffusion-adaptive" if self.adaptive else "diffusion"
        self.K = candidates
        self.seed = seed
        self.params = params or FormationParams()
        self.margin = margin
        self.device = device
        cfg = self.policy.config
        self.n_obs, self.n_act, self.horizon = cfg.n_obs_steps, cfg.n_action_steps, cfg.horizon
        env_dim = cfg.input_features["observation.environment_state"].shape[0]
        self.encoding = next((e for e in ENCODINGS if environment_state_dim(e) == env_dim), None)
        if self.encoding is None:
            raise ValueError(
                f"checkpoint's environment_state has {env_dim} values; no known encoding matches"
            )
        self.model = getattr(self.policy, "ema_diffusion", None) or self.policy.diffusion
        self.template = np.asarray(self.params.graph.template)

    def reset(self, scenes: Scenes) -> None:
        B = len(scenes)
        self.scenes = scenes
        self.env_state = environment_state(scenes.obstacles, scenes.mask, scenes.goal, self.encoding)
        self.history = np.zeros((B, self.n_obs, 7), np.float32)
        self.started = np.zeros(B, dtype=bool)
        self.queue = np.zeros((B, self.n_act, 2))
        self.queue_pos = np.full(B, self.n_act)
        self.generator = torch.Generator().manual_seed(self.seed)
        # MPPI's tuned field: walls x3 within 0.9 m (x30 leaves one-cell valleys the square cannot use).
        self.ctg = (
            cost_to_go(scenes.obstacles, scenes.goal, inflate=0.9, wall_cost=3.0) if self.adaptive else None
        )
        self.replans = 0

    def _noise(self, n: int) -> torch.Tensor:
        return torch.randn((n, self.horizon, 2), generator=self.generator)

    @torch.no_grad()
    def plan(self, idx: np.ndarray, poses: np.ndarray) -> np.ndarray:
        """New action chunks (len(idx), n_action_steps, 2) for episodes idx."""
        n, K = len(idx), self.K
        obs = {
            "observation.state": torch.from_numpy(np.repeat(self.history[idx], K, axis=0)),
            "observation.environment_state": torch.from_numpy(
                np.repeat(np.repeat(self.env_state[idx][:, None], self.n_obs, axis=1), K, axis=0)
            ),
        }
        batch = self.pre(obs)
        # generate_actions' steps, keeping the whole predicted horizon for the adaptive check.
        cond = self.model._prepare_global_conditioning(batch)
        full = self.model.conditional_sample(n * K, global_cond=cond, noise=self._noise(n * K))
        future = (
            self.post(full).cpu().numpy().astype(np.float64)[:, self.n_obs - 1 :]
        )  # from the current step
        self.replans += 1
        if not self.adaptive:
            return future[:, : self.n_act]
        cand = future.reshape(n, K, *future.shape[1:])
        choice, _ = select_safest(
            poses,
            cand,
            self.scenes.obstacles[idx],
            self.ctg[idx],
            self.template,
            self.params.dt,
            self.params.agent_radius,
            self.margin,
        )
        return cand[np.arange(n), choice, : self.n_act]

    def act(self, state: FormationState, idx: np.ndarray) -> np.ndarray:
        obs = midpoint_state(state)
        new = ~self.started[idx]
        if new.any():  # first observation fills the history, as LeRobot's populate_queues does
            self.history[idx[new]] = obs[new][:, None]
            self.started[idx[new]] = True
        self.history[idx[~new]] = np.concatenate([self.history[idx[~new], 1:], obs[~new][:, None]], axis=1)
        need = self.queue_pos[idx] >= self.n_act
        if need.any():
            rows = idx[need]
            self.queue[rows] = self.plan(rows, state.pose[need])
            self.queue_pos[rows] = 0
        a = self.queue[idx, self.queue_pos[idx]]
        self.queue_pos[idx] += 1
        return a
