"""``formation_diffusion``: LeRobot's ``DiffusionPolicy`` plus an EMA of its weights used for inference,
batched candidate sampling with a lean inference path and warm starts, and (with the safety layer or
warm starts on) the per-episode ``Replanner`` (``policy/replanner.py``) behind ``select_action``.

The U-Net, noise scheduler, loss and training forward are LeRobot's; with K = 1, no filter, no
guidance, no warm start and no chunk smoothing (not the default: that is the shipped policy's
safety layer) ``select_action`` is LeRobot's, action queue included.

Both diffusion models (live and EMA) are ``FormationDiffusionModel``: with ``obstacle_encoder="flat"``
(the default) LeRobot's ``DiffusionModel`` exactly (the same weights, the same initial draws); with
"tokens" the U-Net's conditioning per observation step is [state, the obstacle-token encoder's feature]
(``policy.obstacle_tokens``), which every path reads through ``_prepare_global_conditioning``: the
training loss, LeRobot's sampler, ``sample_action_chunks`` (the safety layer, warm starts) and the
lean and trace samplers (the trace holds the U-Net only; the encoder runs eagerly once per replan).

EMA (as diffusers' ``EMAModel`` and the original Diffusion Policy define it):

- ``ema_diffusion`` is a second ``DiffusionModel``, never trained (``requires_grad=False``, left out of
  ``get_optim_params``). ``ema_step`` (a buffer) counts the optimizer steps seen so far. Both are in
  ``model.safetensors``, so a checkpoint and ``--resume=true`` restore them.
- ``update()``, which ``lerobot-train`` calls once after every optimizer step on the unwrapped
  policy, runs diffusers' ``EMAModel.step`` on ``ema_diffusion``'s parameters: decay
  ``EMAModel.get_decay(k)`` at the k-th step (see ``FormationDiffusionConfig``), then
  ``ema <- ema - (1 - decay) (ema - live)``. Buffers are copied.
- In eval mode (``policy.eval()``, as ``lerobot-eval`` and the in-training env evaluation set it),
  ``predict_action_chunk`` and so ``select_action`` run ``ema_diffusion.generate_actions``
  directly: no attribute swap, so concurrent calls cannot see the wrong weights. In train mode
  they use the live model.

Lean inference (``inference_backend``, config field; "eager" is LeRobot's ``conditional_sample``
unchanged): "lean" samples under ``torch.inference_mode`` with the DDIM steps precomputed
(``_DDIMSteps``: diffusers' own timesteps and ``alphas_cumprod``, each step checked once against
diffusers' ``step``); "trace" adds a ``torch.jit`` traced and frozen U-Net (``_TracedUnet``), built
on the first call in eval mode and rebuilt when the weights change (an EMA update, ``load_state_dict``,
a device move). On a CPU it traces ``policy.unet_inference``'s copies of the U-Net: matrix-product
convolutions for calls of up to 64 rows (a B = 1 replan's K candidates), oneDNN's above. Both live
in ``_LeanCache``, a plain attribute: never in the ``state_dict`` or a checkpoint, and a copy or
pickle of the policy starts without them. ``select_action``,
``predict_action_chunk`` and ``sample_action_chunks`` (the engine, the safety layer) all sample
through ``_sample``. The traced graph is not specialised to the batch size (checked at build time on
a second size, and by the tests).

Warm-started replans (``warm_start_step`` j > 0, config field; the streaming / real-time-iteration
idea of reusing the previous plan): at a replan, the part of the episode's previous chunk that was
not executed, shifted to the new time and padded with its last action (``warm_start_guess``), is
noised to the sampler's j-th timestep t_j, x = sqrt(abar_t_j) guess + sqrt(1 - abar_t_j) noise (the
forward process, DDPM eq. 4), and denoised from there (SDEdit): the new plan keeps the way round an
obstacle the last one chose unless the observation says otherwise, and the replan costs j fewer
denoiser calls. An episode's first replan starts from pure noise. With best-of-K every candidate
starts from the guess with its own noise (the first j calls are then not made at all). The
``Replanner`` builds the guess (``warm_start_guess``); ``select_action`` and the engine's controller
both run it.

Multi-GPU (``accelerate launch --multi_gpu --num_processes=N $(which lerobot-train) ...``): DDP
averages the gradients, so after each optimizer step the live weights are identical on every process;
``lerobot-train`` calls ``accelerator.unwrap_model(policy).update()`` on every process after that step,
so every process applies the same EMA update (one per optimizer step, not per sample or per process)
and holds the same EMA weights; the main process saves them. The EMA parameters do not require
gradients, so DDP neither reduces nor waits for them.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from diffusers.schedulers.scheduling_ddim import DDIMScheduler
from diffusers.training_utils import EMAModel
from lerobot.policies.diffusion.modeling_diffusion import DiffusionModel, DiffusionPolicy
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE
from safetensors import safe_open
from torch import Tensor

from lerobot_formation.compat import fast_reads
from lerobot_formation.compat.lerobot_compat import (
    add_weights_loaded_hook,
    denoiser_parts,
    diffusion_unet,
    global_conditioning,
    push_observation,
    queued_history,
    stock_global_conditioning,
    use_conditioning_method,
)
from lerobot_formation.core.controllers.route_pursuit import pursuit_chunk
from lerobot_formation.core.encodings.obstacle_grid import get_encoding
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig
from lerobot_formation.policy.obstacle_tokens import ObstacleTokenEncoder, token_layout
from lerobot_formation.policy.replanner import (
    Replanner,
    check_observation,
    normalize_action,
    policy_sampler,
    unnormalize_action,
)
from lerobot_formation.policy.unet_inference import SMALL_BATCH_ROWS, inference_copy

EMA_PREFIX = "ema_diffusion."
# diffusers' EMAModel defaults, the paper's and the original Diffusion Policy's (only the power is a field)
EMA_MAX_DECAY, EMA_MIN_DECAY, EMA_INV_GAMMA, EMA_UPDATE_AFTER_STEP = 0.9999, 0.0, 1.0, 0


logger = logging.getLogger(__name__)


class _DDIMSteps:
    """Deterministic DDIM steps (eta = 0, as ``conditional_sample`` calls ``DDIMScheduler.step``) of one
    scheduler and step count, precomputed: the timesteps are diffusers' ``set_timesteps``, the
    coefficients its ``alphas_cumprod`` (0-dim float32 tensors, the operations in diffusers' order, so
    the result is bit-identical). ``build`` checks every step once against diffusers' ``step``."""

    def __init__(self, scheduler: DDIMScheduler, num_steps: int):
        cfg = scheduler.config
        scheduler.set_timesteps(num_steps)
        self.timesteps = [int(t) for t in scheduler.timesteps]
        # diffusers' DDIM previous timestep: t - num_train_timesteps // num_inference_steps
        gap = cfg.num_train_timesteps // scheduler.num_inference_steps
        alphas = scheduler.alphas_cumprod
        self.clip = float(cfg.clip_sample_range) if cfg.clip_sample else None
        self.predicts_sample = cfg.prediction_type == "sample"  # the network predicts x0, not the noise
        self.coefs = []
        for t in self.timesteps:
            a, a_prev = alphas[t], alphas[t - gap] if t - gap >= 0 else scheduler.final_alpha_cumprod
            self.coefs.append(((1 - a) ** 0.5, a**0.5, a_prev**0.5, (1 - a_prev) ** 0.5))

    def step(
        self, i: int, eps: Tensor, sample: Tensor, guide: Callable[[Tensor], Tensor] | None = None
    ) -> Tensor:
        """x_t -> x_{t_prev} at the i-th timestep, from the network's output ``eps`` (the predicted
        noise, or with prediction_type "sample" the predicted x_0; diffusers' order of operations).
        ``guide``: x_0 -> a moved x_0 (clearance guidance, ``core.safety.guidance``); the step then goes on
        from the moved estimate, with the noise that is consistent with it and ``sample``."""
        sqrt_beta, sqrt_alpha, sqrt_alpha_prev, sqrt_beta_prev = self.coefs[i]
        if self.predicts_sample:
            x0 = eps
            eps = (sample - sqrt_alpha * x0) / sqrt_beta
        else:
            x0 = (sample - sqrt_beta * eps) / sqrt_alpha
        if self.clip is not None:
            x0 = x0.clamp(-self.clip, self.clip)
        if guide is not None:
            x0 = guide(x0)
            eps = (sample - sqrt_alpha * x0) / sqrt_beta
        return sqrt_alpha_prev * x0 + sqrt_beta_prev * eps

    @classmethod
    def build(cls, scheduler, num_steps: int) -> _DDIMSteps | None:
        """The precomputed steps, or None (diffusers' ``step`` is kept) for another scheduler or
        prediction type, or if any step differs from diffusers' (another diffusers version)."""
        cfg = getattr(scheduler, "config", None)
        if not (
            isinstance(scheduler, DDIMScheduler)
            and cfg.prediction_type in ("epsilon", "sample")
            and not cfg.thresholding
        ):
            return None
        steps = cls(scheduler, num_steps)
        g = torch.Generator().manual_seed(0)
        sample, eps = 1.5 * torch.randn(2, 2, 8, 2, generator=g)
        for i, t in enumerate(steps.timesteps):
            ref = scheduler.step(eps, t, sample).prev_sample
            if not torch.allclose(steps.step(i, eps, sample), ref, rtol=1e-6, atol=1e-6):
                logger.warning(
                    "precomputed DDIM step at t=%d differs from diffusers' DDIMScheduler.step: keeping "
                    "diffusers' step (inference_backend lean/trace)",
                    t,
                )
                return None
        return steps


class _TracedUnet:
    """``torch.jit.trace`` + ``torch.jit.freeze`` of a U-Net in eval mode, on the first call's inputs.

    On a CPU two graphs are traced from ``unet_inference.inference_copy`` copies: one with matrix-product
    convolutions for calls of up to ``SMALL_BATCH_ROWS`` rows (a B = 1 replan's K candidates), one with
    oneDNN's for larger batches (the batched engine); elsewhere the U-Net itself is traced. Frozen
    weights are constants, so the trace remembers which tensors (and versions: every in-place change
    bumps one) it was built from; ``current`` says whether they are unchanged. Each graph is built,
    then checked against the eager U-Net on its own inputs and on one more batch row (the graph must
    not be specialised to the batch size); ``fn`` is None when tracing failed (the eager U-Net is used).
    """

    def __init__(self, unet: torch.nn.Module, sample: Tensor, timestep: Tensor, cond: Tensor):
        self.unet = unet
        self.tensors = [*unet.parameters(), *unet.buffers()]
        self.key = self._fingerprint()
        self.fn = None
        inputs = (sample, timestep, cond)
        graphs = []
        try:
            if sample.device.type == "cpu":
                variants = [inference_copy(unet, matmul_convolutions=True), inference_copy(unet, False)]
            else:
                variants = [unet]
            wider = tuple(torch.cat([x, x[:1]]) for x in inputs)
            expected = [(args, unet(*args)) for args in (inputs, wider)]  # the eager U-Net, once
            for module in variants:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", torch.jit.TracerWarning)
                    # torch 2.11 deprecates torch.jit (torch.compile gains nothing here, see the
                    # benchmark); if a release removes it, this raises and the eager U-Net is kept.
                    warnings.simplefilter("ignore", DeprecationWarning)
                    traced = torch.jit.trace(module, inputs, check_trace=False)
                    fn = torch.jit.freeze(traced.eval())
                for args, want in expected:
                    for _ in range(2):  # the JIT's profiling run, then its optimised graph
                        got = fn(*args)
                        if got.shape != want.shape or not torch.allclose(got, want, rtol=1e-5, atol=1e-5):
                            raise RuntimeError(
                                f"traced U-Net differs from the eager one by {(got - want).abs().max():.2e} "
                                f"at batch size {len(args[0])}"
                            )
                graphs.append(fn)
        except Exception as e:  # noqa: BLE001 (any tracing failure: keep the eager U-Net)
            logger.warning("inference_backend='trace': %s: %s; using the eager U-Net", type(e).__name__, e)
            return
        self.fn = graphs[0] if len(graphs) == 1 else _ByRows(*graphs, SMALL_BATCH_ROWS)

    def _fingerprint(self) -> list[tuple[int, int]]:
        try:
            return [(t.data_ptr(), t._version) for t in self.tensors]
        except RuntimeError:  # weights made under inference_mode keep no version counter
            return [(t.data_ptr(), -1) for t in self.tensors]

    def current(self, unet: torch.nn.Module) -> bool:
        return unet is self.unet and self._fingerprint() == self.key


class _ByRows:
    """Calls ``small`` for inputs of up to ``max_rows`` rows, else ``large``."""

    def __init__(self, small, large, max_rows: int):
        self.small, self.large, self.max_rows = small, large, max_rows

    def __call__(self, sample: Tensor, timestep: Tensor, cond: Tensor) -> Tensor:
        return (self.small if len(sample) <= self.max_rows else self.large)(sample, timestep, cond)


class _LeanCache:
    """Precomputed DDIM steps and traced U-Nets of one policy, per diffusion model (live, EMA). Not a
    module or buffer: never in ``state_dict``; a deep copy or pickle of the policy starts empty."""

    def __init__(self):
        self.steps: dict[int, tuple] = {}  # id(model) -> (scheduler, num_steps, _DDIMSteps | None)
        self.unets: dict[int, _TracedUnet] = {}  # id(model) -> trace (holds the U-Net it traced)

    def ddim(self, model, scheduler, num_steps: int) -> _DDIMSteps | None:
        entry = self.steps.get(id(model))
        if entry is None or entry[0] is not scheduler or entry[1] != num_steps:
            entry = (scheduler, num_steps, _DDIMSteps.build(scheduler, num_steps))
            self.steps[id(model)] = entry
        return entry[2]

    def unet(self, model, unet, sample: Tensor, timestep: Tensor, cond: Tensor):
        traced = self.unets.get(id(model))
        if traced is None or not traced.current(unet):
            traced = self.unets[id(model)] = _TracedUnet(unet, sample, timestep, cond)
        return traced.fn or unet

    def __deepcopy__(self, memo):
        return _LeanCache()

    def __getstate__(self):
        return {}

    def __setstate__(self, state):
        self.__init__()


class FormationDiffusionModel(DiffusionModel):
    """LeRobot's ``DiffusionModel``, whose FiLM conditioning is ``conditioning(batch)``: with
    ``obstacle_encoder="flat"`` LeRobot's own ([state, environment state] per observation step,
    flattened; no other module), with "tokens" [state, ``ObstacleTokenEncoder`` feature (2 token_dim)]
    per step, flattened the same way, and a U-Net built for that width."""

    def __init__(self, config: FormationDiffusionConfig):
        super().__init__(config)
        self.obstacle_tokens: ObstacleTokenEncoder | None = None
        if config.obstacle_encoder == "tokens":
            layout = token_layout(get_encoding(config.obstacle_encoding), config.max_obstacles)
            state_dim = config.robot_state_feature.shape[0]
            self.obstacle_tokens = ObstacleTokenEncoder(state_dim, layout, config.token_dim)
            per_step = state_dim + self.obstacle_tokens.out_dim
            self.unet = diffusion_unet(config, per_step * config.n_obs_steps)

    def conditioning(self, batch: dict[str, Tensor]) -> Tensor:
        """(B, cond) FiLM conditioning of normalised observation histories (B, n_obs_steps, ...)."""
        if self.obstacle_tokens is None:
            return stock_global_conditioning(self, batch)
        state = batch[OBS_STATE]
        features = self.obstacle_tokens(state, batch[OBS_ENV_STATE])
        return torch.cat([state, features], dim=-1).flatten(start_dim=1)

    # -- action_space "route-residual": the chunk is a correction to route pursuit's ---------------------
    def route_prior(self, batch: dict[str, Tensor]) -> Tensor | None:
        """(B, horizon, 2) route pursuit's chunk in normalised units (``core.controllers.route_pursuit.pursuit_chunk``
        from the route hint of the last observation step; the steps before it, never executed, hold its
        first command), or None with ``action_space="velocity"``. Deterministic: a function of the
        observation, so training and every sampler see the same prior."""
        cfg = self.config
        if cfg.action_space != "route-residual":
            return None
        env = batch[OBS_ENV_STATE][:, -1]
        route, goal = get_encoding(cfg.obstacle_encoding).route_hint(
            env.detach().float().cpu().numpy(), cfg.max_obstacles
        )
        ahead = cfg.horizon - cfg.n_obs_steps + 1
        chunk = pursuit_chunk(route, goal, ahead, FormationParams().dt, cfg.action_high[1])
        chunk = np.concatenate([np.repeat(chunk[:, :1], cfg.n_obs_steps - 1, axis=1), chunk], axis=1)
        low, high = np.asarray(cfg.action_low), np.asarray(cfg.action_high)
        return torch.as_tensor(2.0 * (chunk - low) / (high - low) - 1.0, dtype=env.dtype, device=env.device)

    @staticmethod
    def from_residual(prior: Tensor | None, sample: Tensor) -> Tensor:
        """The chunk (normalised actions) of a denoised sample: the sample itself, or with a route prior
        clip(prior + 2 r, -1, 1)."""
        return sample if prior is None else (prior + 2.0 * sample).clamp(-1.0, 1.0)

    def compute_loss(self, batch: dict[str, Tensor]) -> Tensor:
        """LeRobot's loss; with a route prior on the residual r = (a - a_rp) / 2 (in [-1, 1])."""
        prior = self.route_prior(batch)
        if prior is not None:
            batch = {**batch, ACTION: (batch[ACTION] - prior) / 2.0}
        return super().compute_loss(batch)

    def generate_actions(self, batch: dict[str, Tensor], noise: Tensor | None = None) -> Tensor:
        """LeRobot's ``generate_actions`` (the eager sampler), the residual added back."""
        prior = self.route_prior(batch)
        if prior is None:
            return super().generate_actions(batch, noise=noise)
        cond = global_conditioning(self, batch)
        full = self.from_residual(prior, self.conditional_sample(len(cond), global_cond=cond, noise=noise))
        start = self.config.n_obs_steps - 1
        return full[:, start : start + self.config.n_action_steps]


use_conditioning_method(FormationDiffusionModel, "conditioning")


def _residual_guide(
    guide: Callable[[Tensor, Tensor | None], Tensor], prior: Tensor
) -> Callable[[Tensor, Tensor | None], Tensor]:
    """A guide of chunks (normalised actions) as a guide of residuals r = (a - prior) / 2."""

    def moved(x0: Tensor, rows: Tensor | None = None) -> Tensor:
        p = prior if rows is None else prior[rows]
        return (guide(p + 2.0 * x0, rows) - p) / 2.0

    return moved


class FormationDiffusionPolicy(DiffusionPolicy):
    """LeRobot's diffusion policy with an EMA copy of the diffusion model (see the module docstring)."""

    config_class = FormationDiffusionConfig
    name = "formation_diffusion"

    def __init__(self, config: FormationDiffusionConfig, **kwargs):
        if not isinstance(config, FormationDiffusionConfig):
            try:
                got = config.type
            except Exception:  # not a registered PreTrainedConfig at all
                got = None
            raise TypeError(
                "FormationDiffusionPolicy (type 'formation_diffusion') needs a FormationDiffusionConfig, "
                f"got {type(config).__name__} (type {got!r}). A checkpoint of another policy type must be "
                f"loaded with that type's policy class (lerobot.policies.factory.get_policy_class({got!r}))."
            )
        # LeRobot's __init__ builds a DiffusionModel, replaced here; with the RNG state restored the
        # replacement draws the initial weights that one drew (a "flat" model: the same, bit for bit)
        with torch.random.fork_rng(devices=[]):
            super().__init__(config, **kwargs)
        self.diffusion = FormationDiffusionModel(config)
        fast_reads.install()  # a formation run: fast windowed reads of formation datasets only
        self._lean = _LeanCache()  # inference_backend "lean" / "trace" (never in the state_dict)
        self.ema_diffusion: FormationDiffusionModel | None = None
        self._ema: EMAModel | None = None
        if config.use_ema:
            self.ema_diffusion = FormationDiffusionModel(config)
            self.ema_diffusion.load_state_dict(self.diffusion.state_dict())
            self.ema_diffusion.requires_grad_(False)
            self.register_buffer("ema_step", torch.zeros((), dtype=torch.long))
            # The schedule and the update are diffusers' own; this object holds no weights (its
            # shadow parameters are pointed at ema_diffusion's for the duration of each update).
            self._ema = EMAModel(
                [],
                decay=EMA_MAX_DECAY,
                min_decay=EMA_MIN_DECAY,
                update_after_step=EMA_UPDATE_AFTER_STEP,
                use_ema_warmup=True,
                inv_gamma=EMA_INV_GAMMA,
                power=config.ema_power,
                foreach=True,
            )

    # -- inference: batched chunk sampling and the safety layer -------------------------------------
    @property
    def inference_model(self) -> DiffusionModel:
        """The model inference uses: the EMA copy in eval mode (if kept), else the live one."""
        return self.ema_diffusion if self.ema_diffusion is not None and not self.training else self.diffusion

    @torch.inference_mode()
    def sample_action_chunks(
        self,
        batch: dict[str, Tensor],
        num_candidates: int = 1,
        noise: Tensor | None = None,
        warm_start: tuple[Tensor, Tensor] | None = None,
        warm_start_step: int | None = None,
        warm_all: bool = False,
        guide: Callable[[Tensor, Tensor | None], Tensor] | None = None,
    ) -> Tensor:
        """K candidate chunks per observation in one batched denoiser call.

        ``batch`` holds normalised observation histories (B, n_obs_steps, ...), as the preprocessor and
        the queues give them. Returns (B, K, horizon - n_obs_steps + 1, 2) normalised actions, from the
        current step on (the first ``n_action_steps`` are what ``select_action`` executes). ``noise``
        (B * K, horizon, 2), if given, is the initial noise, candidates of one observation adjacent.
        ``warm_start`` = (guess (B, horizon, 2) normalised, use (B,) bool): with ``warm_start_step``
        j > 0 (default: the config's) the rows of ``use`` start at the sampler's j-th timestep from
        their guess (see the module docstring): the first candidate of a row, or with ``warm_all`` all
        K, each from the same guess with its own noise. ``guide(x0, rows)``: at every DDIM step the
        estimate x0 (n, horizon, 2) of the rows ``rows`` of the B * K samples (a bool mask; None: all)
        is moved by it before the step goes on (``_DDIMSteps.step``; the lean and trace backends).
        """
        model = self.inference_model
        cond = global_conditioning(model, batch)  # (B, cond)
        B, K = cond.shape[0], int(num_candidates)
        # a caller's noise and guess (a bench seeds them on the CPU) go where the model runs
        if noise is not None:
            noise = noise.to(cond.device, cond.dtype)
        if warm_start is not None:
            warm_start = tuple(x.to(cond.device) for x in warm_start)
        prior = model.route_prior(batch)
        if K > 1:
            cond = cond.repeat_interleave(K, dim=0)
            prior = None if prior is None else prior.repeat_interleave(K, dim=0)
        if warm_start is not None and K > 1:  # the first candidate of each row continues its last plan
            guess, use = (x.repeat_interleave(K, dim=0) for x in warm_start)
            if not warm_all:
                use = use & ((torch.arange(B * K, device=use.device) % K) == 0)
            warm_start = (guess, use)
        if prior is not None:  # the sampler works on residuals: the guess and the guide in its units
            if warm_start is not None:
                warm_start = ((warm_start[0].to(prior.dtype) - prior) / 2.0, warm_start[1])
            if guide is not None:
                guide = _residual_guide(guide, prior)
        full = model.from_residual(
            prior, self._sample(model, cond, noise, warm_start, warm_start_step, guide)
        )
        return full[:, self.config.n_obs_steps - 1 :].reshape(B, K, -1, full.shape[-1])

    def _sample(
        self,
        model: DiffusionModel,
        cond: Tensor,
        noise: Tensor | None = None,
        warm_start: tuple[Tensor, Tensor] | None = None,
        warm_start_step: int | None = None,
        guide: Callable[[Tensor, Tensor | None], Tensor] | None = None,
    ) -> Tensor:
        """(len(cond), horizon, action_dim) denoised samples of ``model`` for the conditioning vectors
        ``cond``, from ``noise`` (else fresh ``torch.randn``, as ``conditional_sample`` draws it), on
        the configured ``inference_backend`` (see the module docstring); ``warm_start`` as in
        ``sample_action_chunks``, per row of ``cond``."""
        backend = self.config.inference_backend
        if warm_start_step is None:
            warm_start_step = self.config.warm_start_step
        j = warm_start_step if warm_start is not None and bool(warm_start[1].any()) else 0
        parts = None if backend == "eager" and j == 0 else denoiser_parts(model)
        if parts is None and guide is None:
            return model.conditional_sample(len(cond), global_cond=cond, noise=noise)
        if guide is not None and (parts is None or backend == "eager"):
            raise ValueError(
                "clearance guidance (sampling_guidance > 0) runs in the lean and trace samplers; "
                f"inference_backend is {backend!r}: pass --policy.inference_backend=trace"
            )
        unet, scheduler, num_steps, shape = parts
        with torch.inference_mode():
            if noise is None:
                p = next(model.parameters())
                noise = torch.randn((len(cond), *shape), dtype=p.dtype, device=p.device)
            sample = noise
            ddim = None if backend == "eager" else self._lean.ddim(model, scheduler, num_steps)
            if guide is not None and ddim is None:
                raise ValueError(
                    "clearance guidance (sampling_guidance > 0) needs DDIM sampling (noise_scheduler_type "
                    f"'DDIM' at inference), got scheduler {type(scheduler).__name__}"
                )
            if ddim is not None:
                timesteps = ddim.timesteps
            else:  # the eager backend or another scheduler: diffusers' own steps
                scheduler.set_timesteps(num_steps)
                timesteps = scheduler.timesteps
            net = unet
            if backend == "trace" and not self.training and not self.config.compile_model:
                t_batch = torch.full(sample.shape[:1], timesteps[0], dtype=torch.long, device=sample.device)
                net = self._lean.unet(model, unet, sample, t_batch, cond)  # traced on these inputs
            warm = None
            if j:
                if j >= len(timesteps):
                    raise ValueError(
                        f"warm_start_step must be below the sampler's {len(timesteps)} steps, got {j}"
                    )
                guess, warm = warm_start[0].to(sample.dtype), warm_start[1].to(sample.device)
                t_j = torch.full(sample.shape[:1], int(timesteps[j]), dtype=torch.long, device=sample.device)
                noised = scheduler.add_noise(guess, sample, t_j)  # the forward process, DDPM eq. 4
                sample = torch.where(warm[:, None, None], noised, sample)
            for i, t in enumerate(timesteps):
                rows = None if warm is None or i >= j else ~warm  # before t_j: the cold rows only
                if rows is not None and not rows.any():
                    continue
                x = sample if rows is None else sample[rows]
                c = cond if rows is None else cond[rows]
                t_batch = torch.full(x.shape[:1], t, dtype=torch.long, device=x.device)
                eps = net(x, t_batch, c)
                if ddim is None:
                    x = scheduler.step(eps, t, x).prev_sample
                else:
                    moved = None if guide is None else functools.partial(guide, rows=rows)
                    x = ddim.step(i, eps, x, moved)
                if rows is None:
                    sample = x
                else:  # sample is torch.where's own tensor here, never the caller's noise
                    sample[rows] = x
        return sample

    def unnormalize_action(self, action: Tensor) -> Tensor:
        """Normalised actions (..., 2) in [-1, 1] -> [v, omega] with the fixed bounds (MIN_MAX)."""
        return unnormalize_action(action)

    def normalize_action(self, action: Tensor) -> Tensor:
        return normalize_action(action)

    def reset(self):
        """LeRobot's reset (observation queues), and a fresh start of ``self.replanner`` (a new one, with
        the same experiment settings, if the config was replaced)."""
        super().reset()
        replanner = getattr(self, "replanner", None)
        if replanner is None or replanner.config is not self.config:
            experiment = replanner.experiment if replanner else None
            self.replanner = Replanner.from_config(self.config, policy_sampler(self), experiment)
        else:
            replanner.reset()

    @property
    def safety_stats(self) -> dict[str, int]:
        """Counts of ``select_action``'s replanner since the last ``reset`` (``policy.replanner.STAT_KEYS``)."""
        return self.replanner.stats

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], noise: Tensor | None = None) -> Tensor:
        """``DiffusionPolicy.select_action`` (same observation history). With the safety layer
        (``num_candidates > 1`` or ``safety_filter != "none"``) or warm-started replans, the policy's
        ``Replanner`` runs instead of LeRobot's action queue: each episode of the batch keeps its own
        chunk and replans on its own (best-of-K, the CBF filter, replan on intervention, warm starts),
        as the engine does. Counts go to ``self.safety_stats``.
        """
        check_observation(batch, self.config.input_features, self._model_dtype())
        if not self.config.plans_per_episode:
            return super().select_action(batch, noise=noise)
        batch = {k: v for k, v in batch.items() if k != ACTION}
        env_now = batch[OBS_ENV_STATE]
        push_observation(self, batch)
        if self.replanner.plan is None or len(self.replanner.plan) != len(env_now):
            self.replanner.start(len(env_now), env_now.device)

        def history(rows: Tensor) -> dict[str, Tensor]:
            stacked = {k: v[rows] for k, v in queued_history(self, batch).items()}
            self._check_observation_sizes(stacked)
            return stacked

        return self.replanner.act(env_now, history, noise=noise)

    def reconfigure(self, **changes) -> None:
        """Run with a copy of the config with ``changes`` (``dataclasses.replace``, so its checks run);
        the diffusion models share the new config."""
        self.config = dataclasses.replace(self.config, **changes)
        for model in (self.diffusion, self.ema_diffusion):
            if model is not None:
                model.config = self.config
        self.reset()

    def _model_dtype(self) -> torch.dtype:
        return next(self.diffusion.parameters()).dtype

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path, **kwargs):
        """``PreTrainedPolicy.from_pretrained``, after checking the checkpoint's processor pipelines
        (``checkpoint_files.check_processor_configs``): ``lerobot-eval`` and ``lerobot-train`` load the
        policy first and its processors next, so a pipeline naming an unregistered class is refused
        before LeRobot would import and call it. A hub id is checked on the files it downloads (when
        they cannot be fetched, LeRobot's own download of them fails later too)."""
        from lerobot_formation.policy.checkpoint_files import PROCESSOR_CONFIGS, check_processor_config

        folder = Path(pretrained_name_or_path)
        if folder.is_dir():
            files = [folder / name for name in PROCESSOR_CONFIGS if (folder / name).is_file()]
        else:
            files = _hub_processor_configs(str(pretrained_name_or_path), kwargs)
        for f in files:
            check_processor_config(f)
        return super().from_pretrained(pretrained_name_or_path, **kwargs)

    def get_optim_params(self) -> dict:
        """The live diffusion model's parameters only (never the EMA copy)."""
        return self.diffusion.parameters()

    def ema_decay(self, step: int) -> float:
        """EMA decay applied at optimizer step ``step`` (1-based), diffusers' ``EMAModel.get_decay``."""
        if self._ema is None:
            raise RuntimeError("use_ema is False: this policy keeps no EMA")
        return float(self._ema.get_decay(step))

    @torch.no_grad()
    def update(self) -> None:
        """EMA update; ``lerobot-train`` calls it once after every optimizer step."""
        if self._ema is None:
            return
        ema_params = list(self.ema_diffusion.parameters())
        live_params = list(self.diffusion.parameters())
        self._ema.shadow_params = ema_params
        self._ema.optimization_step = int(self.ema_step)
        try:
            self._ema.step(live_params)  # increments optimization_step, then updates ema_params in place
        finally:
            self._ema.shadow_params = []
        self.ema_step.fill_(self._ema.optimization_step)
        for ema_buf, live_buf in zip(self.ema_diffusion.buffers(), self.diffusion.buffers(), strict=True):
            ema_buf.copy_(live_buf)

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], noise: Tensor | None = None) -> Tensor:
        """``DiffusionPolicy.predict_action_chunk``, with the EMA model in eval mode.

        Returns (B, n_action_steps, action_dim) actions (normalized, as the postprocessor expects).
        """
        self._check_observation_sizes(batch)
        if self.config.inference_backend != "eager":
            batch = queued_history(self, batch)
            model = self.inference_model
            full = self._sample(model, global_conditioning(model, batch), noise)
            full = model.from_residual(model.route_prior(batch), full)
            start = self.config.n_obs_steps - 1  # as DiffusionModel.generate_actions slices
            return full[:, start : start + self.config.n_action_steps]
        if self.ema_diffusion is None or self.training:
            return super().predict_action_chunk(batch, noise=noise)
        # As DiffusionPolicy does: the observation history (B, n_obs_steps, ...) from the queues
        # select_action fills, or an offline batch as given. No image features here.
        batch = queued_history(self, batch)
        return self.ema_diffusion.generate_actions(batch, noise=noise)

    def _check_observation_sizes(self, batch: dict[str, Tensor]) -> None:
        """Observations must have the sizes the policy was trained on (e.g. the env's obstacle encoding)."""
        for key, feature in self.config.input_features.items():
            if key in batch and batch[key].shape[-1] != feature.shape[0]:
                hint = ""
                if key == OBS_ENV_STATE and self.config.obstacle_encoding is not None:
                    hint = f" Evaluate with --env.obstacle_encoding={self.config.obstacle_encoding}."
                raise ValueError(
                    f"'{key}' has {batch[key].shape[-1]} values per step, but this policy was trained on "
                    f"{feature.shape[0]}.{hint}"
                )


def _hub_processor_configs(repo_id: str, kwargs: dict) -> list[Path]:
    """The processor pipeline files of a hub checkpoint, downloaded as ``from_pretrained`` would."""
    from huggingface_hub import hf_hub_download

    from lerobot_formation.policy.checkpoint_files import PROCESSOR_CONFIGS

    options = {k: kwargs[k] for k in ("revision", "cache_dir", "token", "local_files_only") if k in kwargs}
    files = []
    for name in PROCESSOR_CONFIGS:
        try:
            files.append(Path(hf_hub_download(repo_id=repo_id, filename=name, **options)))
        except Exception as e:  # noqa: BLE001  (offline, missing file: LeRobot's load fails the same way)
            logger.debug("processor config %s of %s not checked: %s", name, repo_id, e)
    return files


def _ema_from_live_if_missing(model: FormationDiffusionPolicy, model_file: str) -> FormationDiffusionPolicy:
    """After LeRobot loads ``model_file``: a checkpoint without EMA weights (trained with
    use_ema=false) starts the EMA from the live weights, with a warning, instead of from the
    initial ones."""
    if model.ema_diffusion is not None:
        with safe_open(model_file, framework="pt") as f:
            has_ema = any(k.startswith(EMA_PREFIX) for k in f.keys())  # noqa: SIM118
        if not has_ema:
            logging.warning(
                "%s holds no EMA weights (trained with use_ema=false?): the EMA starts from the live "
                "weights with ema_step=0.",
                model_file,
            )
            model.ema_diffusion.load_state_dict(model.diffusion.state_dict())
            model.ema_step.zero_()
    return model


add_weights_loaded_hook(FormationDiffusionPolicy, _ema_from_live_if_missing)
