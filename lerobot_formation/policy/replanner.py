"""The replan loop of a ``formation_diffusion`` policy: the one implementation that ``select_action``
(so ``lerobot-eval``) and the engine's diffusion controller (``bench``) both run.

A ``Replanner`` keeps the plan bookkeeping and the sampling; the safety layer is a unit of its own in
the numpy core (``core.safety.layer.SafetyLayer``), which the replanner calls with numpy arrays in
physical units. It is given a sampler (a callable with the signature of
``FormationDiffusionPolicy.sample_action_chunks``: the policy passes ``policy_sampler(policy)``), never
the policy itself.

Per episode of a batch it owns the kept chunk (normalised, the whole predicted horizon from the step
it was planned at), the position of the next action in it, the actions executed since that replan and
the last executed action; the layer owns its own per-episode state (commands in flight, trackers).
``act(rows, env_now, history)`` returns the next action (normalised) of the episodes ``rows``; an
episode whose chunk is used up (``n_action_steps`` actions ran), whose last action the filter changed,
or (best-of-K) whose kept chunk no longer passes the layer's recheck on this step's view replans
first:

1. warm start (``warm_start_step`` j > 0): the unexecuted rest of the episode's last chunk, shifted to
   the new window and padded with its last action (``warm_start_guess``), is the guess every
   candidate starts from at the sampler's j-th timestep, each with its own noise; an episode's first
   replan samples from pure noise;
2. K = ``num_candidates`` candidates in one batched sampler call; with ``guidance`` every denoising
   step moves them away from the view's obstacles (``SafetyLayer.clearance_step``, ``_guide``);
   ``chunk_smoothing`` smooths them;
3. blending (``ReplanExperiment.blend_steps``, experiments only): the new chunks' first actions are
   blended from the last executed one (``core.safety.replan_blend``);
4. choice: with K > 1 the layer's best-of-K (``SafetyLayer.choose``: footprint check, cost-to-go
   progress, route pursuit's proposal, escapes, coherence with the plan it replaces unless the
   filter cut that plan short); with K = 1 the sample;
5. filter (the layer's ``filter`` "cbf"): every executed action passes ``SafetyLayer.filter``; an
   episode whose action it changed replans at its next step (the plan met a barrier);
6. recheck (K > 1): at each step before 1-5, the rest of the kept chunk is checked again on the new
   view (``SafetyLayer.recheck``); where it fails, the episode replans at once. A chunk kept where
   nothing was safe (the widest fallback) is rechecked like any other, so such an episode replans at
   every step while its rest still fails.

What the layer sees of an episode at a step is a ``core.safety.layer.SafetyView``, built once per
step from the raw observation (``view``). All of it starts afresh with each episode (``start``).

The replanner's own settings are a ``PlanSettings`` (the sampler's too: chunk smoothing and the
guidance step, used with K = 1 as well, and the observation's layout the layer decodes) and the
layer's a ``core.safety.layer.SafetySettings``; ``Replanner.from_config`` reads both from a policy config (the policy's own, or a copy made with
``dataclasses.replace`` for a bench controller or an ablation row, which runs the config's checks).
The settings of the ablation study that the shipped policy does not use are a ``ReplanExperiment``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, fields

import numpy as np
import torch
from torch import Tensor

from lerobot_formation.core.safety import filters as safety
from lerobot_formation.core.safety.layer import SafetyLayer, SafetySettings, SafetyView, action_bounds
from lerobot_formation.core.safety.replan_blend import blend_replan, smooth_chunks

ACTION_DIM = 2  # [v, omega]
STAT_KEYS = (
    "replans",
    "replans_none_safe",
    "escapes",
    "stops",
    "steps",
    "filter_interventions",
    "proposals",
    "rechecks_failed",
    "searched",
)
# a sampler: (normalised observation histories, K, noise=, warm_start=, warm_start_step=, warm_all=,
# guide=) -> (B, K, chunk_length, 2) normalised chunks (``FormationDiffusionPolicy.sample_action_chunks``)
Sampler = Callable[..., Tensor]


@dataclass(frozen=True)
class ReplanExperiment:
    """Replan settings of the ablation study (``scripts/ablation.py``), not of the shipped policy; the
    defaults are what the policy runs.

    Args:
        blend_steps: m >= 0; a new chunk's first m actions are blended from the last executed action
            (``core.safety.replan_blend``) before best-of-K scores them. 0: plain chunk execution.
        escape_advantage: None: the escape manoeuvres of best-of-K are used only when no sampled chunk
            is safe. A number [m]: a safe manoeuvre is also kept when its cost-to-go progress beats
            every safe sampled chunk's by that much.
        blocked_fallback: "widest" (the sampled chunk with the largest predicted clearance) or "stop"
            when nothing is safe (``core.safety.filters.select_chunk``).
        sampled: False: nothing is sampled; best-of-K's candidates are route pursuit's proposal and
            the escapes, under the same check, filter and recheck. The safety layer without the
            learned planner: the baseline the layer's rows are measured against (needs a route
            encoding). With K = 1 and ``PlanSettings.guidance``, the plan is
            route pursuit's chunk moved by the clearance guidance ``PlanSettings.denoising_steps``
            times: the baseline of guided sampling.
    """

    blend_steps: int = 0
    escape_advantage: float | None = None
    blocked_fallback: str = "widest"
    sampled: bool = True

    def __post_init__(self):
        if self.blend_steps < 0:
            raise ValueError(f"blend_steps must be >= 0, got {self.blend_steps}")
        if self.escape_advantage is not None and not self.escape_advantage >= 0:
            raise ValueError(f"escape_advantage must be None or >= 0 [m], got {self.escape_advantage}")
        if self.blocked_fallback not in safety.BLOCKED_FALLBACKS:
            raise ValueError(
                f"blocked_fallback must be one of {safety.BLOCKED_FALLBACKS}, got {self.blocked_fallback!r}"
            )


@dataclass(frozen=True)
class PlanSettings:
    """The replanner's own settings (plan bookkeeping, sampling and the observation's layout): a policy
    config's fields of the same names (``from_config``; ``guidance`` is ``sampling_guidance``). The
    defaults are the shipped checkpoint's.

    Attributes:
        horizon: the sampled window's length (steps).
        n_obs_steps: observation steps; the window starts ``n_obs_steps - 1`` steps before the current
            one, so a chunk holds ``chunk_length`` actions from the current step on.
        n_action_steps: actions run before a scheduled replan.
        num_candidates: K chunks sampled per replan; with K > 1 the layer keeps the best.
        warm_start_step: j; a replan's candidates start at the sampler's j-th timestep from the rest
            of the last plan (0: from pure noise).
        denoising_steps: the sampler's steps from noise (``num_inference_steps``, else
            ``num_train_timesteps``): how often a guided proposal is moved
            (``ReplanExperiment.sampled``).
        chunk_smoothing: [passes] of the [1, 2, 1] / 4 kernel over every sampled chunk, and over
            route pursuit's blended proposal (``chunk_smoothing``).
        guidance: eta, the step of the sampler's clearance guidance (``SafetyLayer.clearance_step``);
            0: none (``sampling_guidance``).
        obstacle_encoding: the observation's layout the layer decodes (``obstacle_encoding``).
        max_obstacles: its obstacle slots, None: the encoding's default (``max_obstacles``).
    """

    horizon: int = 16
    n_obs_steps: int = 2
    n_action_steps: int = 4
    num_candidates: int = 10
    warm_start_step: int = 1
    denoising_steps: int = 4
    chunk_smoothing: int = 2
    guidance: float = 1.0
    obstacle_encoding: str = "nearest+route"
    max_obstacles: int | None = None

    @classmethod
    def from_config(cls, config) -> PlanSettings:
        return cls(
            horizon=config.horizon,
            n_obs_steps=config.n_obs_steps,
            n_action_steps=config.n_action_steps,
            num_candidates=config.num_candidates,
            warm_start_step=config.warm_start_step,
            denoising_steps=config.num_inference_steps or config.num_train_timesteps,
            chunk_smoothing=config.chunk_smoothing,
            guidance=config.sampling_guidance,
            obstacle_encoding=config.obstacle_encoding,
            max_obstacles=config.max_obstacles,
        )

    @staticmethod
    def from_config_fields(values: dict) -> dict:
        """The settings (name -> value) of the policy config fields among ``values`` that are read
        as they are (``from_config``; the others are left out)."""
        names = {f.name for f in fields(PlanSettings)} - {"guidance", "denoising_steps"}
        out = {name: values[name] for name in names if name in values}
        if "sampling_guidance" in values:
            out["guidance"] = values["sampling_guidance"]
        return out

    @property
    def chunk_length(self) -> int:
        return self.horizon - self.n_obs_steps + 1


@functools.cache
def _action_scale() -> tuple[Tensor, Tensor]:
    low, high = action_bounds()
    return torch.tensor(low, dtype=torch.float32), torch.tensor(high, dtype=torch.float32)


def unnormalize_action(action: Tensor) -> Tensor:
    """Normalised actions (..., 2) in [-1, 1] -> [v, omega] with the env's fixed bounds (MIN_MAX, as
    the policy's postprocessor), on the CPU."""
    low, high = _action_scale()
    return (action.float().cpu() + 1) / 2 * (high - low) + low


def normalize_action(action: Tensor) -> Tensor:
    """[v, omega] (..., 2) -> normalised actions in [-1, 1] (``unnormalize_action``'s inverse)."""
    low, high = _action_scale()
    return (action.float() - low) / (high - low) * 2 - 1


@dataclass(frozen=True, eq=False)
class PolicySampler:
    """A policy's ``sample_action_chunks`` as a replanner's sampler, looked up at each call (so a
    method patched on the policy or its class, e.g. by a profiler, is what runs)."""

    policy: object

    def __call__(self, *args, **kwargs) -> Tensor:
        return self.policy.sample_action_chunks(*args, **kwargs)


def policy_sampler(policy) -> PolicySampler:
    """The sampler a policy hands its replanner (``PolicySampler``)."""
    return PolicySampler(policy)


def check_observation(batch: dict[str, Tensor], input_features: dict, dtype: torch.dtype) -> None:
    """Refuse an observation the policy cannot use: each input feature in ``batch`` must be a tensor of
    the model's floating dtype ``dtype`` holding finite numbers. One NaN would make every action NaN
    (and, with warm starts, every later plan of the episode). The error names the key, the problem and
    where. Called at the top of ``select_action`` and by the engine before each replan."""
    for key in input_features:
        value = batch.get(key)
        if value is None:
            continue
        if not isinstance(value, Tensor):
            raise TypeError(f"observation '{key}' must be a torch.Tensor, got {type(value).__name__}")
        if value.dtype != dtype:
            raise TypeError(
                f"observation '{key}' has dtype {value.dtype}, but the policy computes in {dtype}: pass it "
                f"through the policy's preprocessor, or convert it (tensor.to({dtype}))"
            )
        finite = torch.isfinite(value)
        if not bool(finite.all()):
            where = torch.nonzero(~finite)[0].tolist()
            raise ValueError(
                f"observation '{key}' holds a non-finite value ({value[tuple(where)].item()} at index {where}); "
                "the policy refuses NaN and inf observations (a broken sensor or env?)"
            )


def check_finite_chunks(chunks: Tensor) -> None:
    """Refuse sampled action chunks with a NaN or inf before they are executed or kept as the warm
    start of the next replan (where a NaN would poison every later plan of the episode)."""
    finite = torch.isfinite(chunks)
    if not bool(finite.all()):
        rows = sorted({int(r) for r in torch.nonzero(~finite)[:, 0]})
        raise FloatingPointError(
            f"the policy sampled a non-finite action chunk (batch rows {rows[:8]}); it is neither executed nor "
            "kept for warm starts. Non-finite weights or noise?"
        )


def warm_start_guess(previous: Tensor, executed: Tensor, n_obs_steps: int, horizon: int) -> Tensor:
    """The warm start of a replan (B, horizon, A): the previous chunk ``previous`` (B, T, A), its
    actions from the previous replan's step on, after ``executed`` (B,) of them ran, shifted to the new
    sample's window (which starts ``n_obs_steps - 1`` steps before the current one) and padded with its
    last action."""
    offset = executed.to(torch.long) - (n_obs_steps - 1)  # index in ``previous`` of the window's start
    idx = (offset[:, None] + torch.arange(horizon, device=previous.device)[None]).clamp(
        0, previous.shape[1] - 1
    )
    return torch.gather(previous, 1, idx[..., None].expand(-1, -1, previous.shape[-1]))


class Replanner:
    """Per-episode chunks, sampling and replans of one batch of episodes, around a safety layer
    (module docstring).

    Args:
        settings: the plan's settings (default: the shipped checkpoint's, ``PlanSettings()``).
        safety: the safety layer's settings (default: the shipped default's, ``SafetySettings()``).
        sampler: draws the candidates (``Sampler``); None: nothing can be sampled (a replanner of
            ``ReplanExperiment(sampled=False)``).
        experiment: ablation settings (``ReplanExperiment``); default none.
    """

    def __init__(
        self,
        settings: PlanSettings | None = None,
        safety: SafetySettings | None = None,
        sampler: Sampler | None = None,
        experiment: ReplanExperiment | None = None,
    ):
        self.settings = PlanSettings() if settings is None else settings
        self.experiment = experiment or ReplanExperiment()
        self.sampler = sampler
        self.config = None  # the policy config it was built from (``from_config``), if any
        ex = self.experiment
        if ex.blend_steps > self.chunk_length:
            raise ValueError(
                f"blend_steps must be in [0, {self.chunk_length}] (the chunk's length), got {ex.blend_steps}"
            )
        ps = self.settings
        self.layer = SafetyLayer(
            safety,
            encoding=ps.obstacle_encoding,
            max_obstacles=ps.max_obstacles,
            blend_steps=ex.blend_steps,
            escape_advantage=ex.escape_advantage,
            blocked_fallback=ex.blocked_fallback,
        )
        s = self.layer.settings
        if not ex.sampled and not (self.uses_layer and self.layer.encoding.map):
            raise ValueError(
                "a replanner that samples nothing (ReplanExperiment.sampled=False) needs route pursuit's "
                "proposal and a safety layer: a route-encoding config with num_candidates > 1, a filter "
                f"or guidance, got obstacle_encoding={ps.obstacle_encoding!r}, "
                f"num_candidates={ps.num_candidates}, safety_filter={s.filter!r}, "
                f"sampling_guidance={ps.guidance}"
            )
        self._counts = {"replans": 0, "steps": 0}
        self.plan: Tensor | None = None

    @classmethod
    def from_config(
        cls, config, sampler: Sampler | None = None, experiment: ReplanExperiment | None = None
    ) -> Replanner:
        """The replanner of a policy config: its ``PlanSettings`` and ``SafetySettings``
        (``config`` is kept as ``.config``)."""
        out = cls(PlanSettings.from_config(config), SafetySettings.from_config(config), sampler, experiment)
        out.config = config
        return out

    @property
    def chunk_length(self) -> int:
        return self.settings.chunk_length

    @property
    def stats(self) -> dict[str, int]:
        """The counts since ``reset`` (``STAT_KEYS``): replans and steps, and the layer's
        (``core.safety.layer.LAYER_STAT_KEYS``)."""
        counts = {**self._counts, **self.layer.stats}
        return {k: counts[k] for k in STAT_KEYS}

    @property
    def uses_layer(self) -> bool:
        """Whether anything reads the observed obstacles: best-of-K, the filter or the guidance (a
        policy config's ``safety_layer``)."""
        ps = self.settings
        return ps.num_candidates > 1 or self.layer.settings.filter != "none" or ps.guidance > 0

    @property
    def best_of(self) -> bool:
        """Whether replans choose among candidates (K > 1, or no samples: the proposal and escapes,
        except the guided proposal alone of K = 1 with ``guidance``)."""
        return self.settings.num_candidates > 1 or not (self.experiment.sampled or self.settings.guidance)

    def reset(self, batch_size: int | None = None, device: torch.device | str = "cpu") -> None:
        """Forget every episode's plan (and with ``batch_size``, start ``batch_size`` episodes); the stats
        start from zero."""
        self._counts = {"replans": 0, "steps": 0}
        self.layer.reset()
        self.plan = None
        if batch_size is not None:
            self.start(batch_size, device)

    def start(self, B: int, device: torch.device | str = "cpu") -> None:
        """Start ``B`` episodes with no plan (each replans at its first ``act``), and the layer's."""
        A, n = ACTION_DIM, self.settings.n_action_steps
        self.plan = torch.zeros(B, self.chunk_length, A, device=device)  # normalised, whole chunk
        self.plan_pos = torch.full((B,), n, dtype=torch.long)  # next action
        self.executed = torch.zeros(B, dtype=torch.long)  # actions run since the episode's last replan
        self.last_action = torch.zeros(B, A, device=device)  # normalised
        self.has_last = torch.zeros(B, dtype=torch.bool)
        self.layer.start(B)

    def needs_replan(self, rows: Tensor) -> Tensor:
        """Which of ``rows`` replan at their next ``act`` (B,) bool."""
        if self.plan is None:
            return torch.ones(len(rows), dtype=torch.bool)
        return self.plan_pos[rows] >= self.settings.n_action_steps

    @torch.no_grad()
    def act(
        self,
        env_now: Tensor,
        history: Callable[[Tensor], dict[str, Tensor]],
        rows: Tensor | None = None,
        noise: Tensor | Callable[[Tensor, int], Tensor] | None = None,
    ) -> Tensor:
        """The next action (len(rows), A), normalised, of episodes ``rows`` (default: all of the batch).

        ``env_now`` (len(rows), D): their current raw ``observation.environment_state`` (what the
        safety layer reads); ``history(sub)`` the normalised observation histories (len(sub),
        n_obs_steps, ...) of the episodes ``sub`` (indices into the batch) that replan; ``noise`` the
        initial noise (n * K, horizon, A) of the n replanning episodes, or a function (their indices
        into the batch (n,), K) -> that noise, K rows per episode in its order, or None (fresh
        ``torch.randn``). With a function (the engine's: one stream per episode) each replanning
        episode's K candidates also run in a sampler call of their own, so that an episode's chunks
        do not depend on which episodes replan with it: the U-Net's float rounding depends on the
        call's row count (a matrix-vector product for one observation, matrix-product convolutions up
        to ``SMALL_BATCH_ROWS`` rows, oneDNN's above), and ~1e-6 apart is enough to flip a later
        choice of the safety layer. The calls cost about twice the sampler's time of a large batch.
        """
        n = self.settings.n_action_steps
        if rows is None:
            rows = torch.arange(len(env_now))
        if self.plan is None:
            self.start(len(rows), env_now.device)
        view = self.view(env_now, rows) if self.uses_layer else None
        if self.best_of:
            self._recheck(rows, view)
        need = rows[self.plan_pos[rows] >= n]
        if len(need):
            at = torch.nonzero(self.plan_pos[rows] >= n).flatten()
            self._replan(need, None if view is None else view[at.numpy()], history(need), noise)
        action = self.plan[rows, self.plan_pos[rows]]
        self.plan_pos[rows] += 1
        self.executed[rows] += 1
        self._counts["steps"] += len(rows)
        if self.layer.settings.filter != "none":
            action, changed = self.filter(view, action)
            self.plan_pos[rows[torch.from_numpy(changed)]] = n  # the plan met a barrier: replan next step
        self.last_action[rows] = action.to(self.last_action.dtype)
        self.has_last[rows] = True
        if view is not None and self.layer.tracks_commands:
            self.layer.send(rows.cpu().numpy(), unnormalize_action(action).numpy().astype(np.float64))
        return action

    def view(self, env_state: Tensor, rows: Tensor) -> SafetyView:
        """The layer's ``SafetyView`` of episodes ``rows`` at this step from their raw observation
        (len(rows), D) (``SafetyLayer.view``; call it once per step)."""
        env = env_state.float().cpu().numpy() if isinstance(env_state, Tensor) else np.asarray(env_state)
        return self.layer.view(env, rows.cpu().numpy())

    def _recheck(self, rows: Tensor, view: SafetyView) -> None:
        """Best-of-K's recheck: episodes ``rows`` whose plan is under way check its rest on this step's
        ``view`` (``SafetyLayer.recheck``); those where it fails replan now (a chunk kept where
        nothing was safe, the widest fallback, too: such an episode replans at every step while its
        rest still fails)."""
        n = self.settings.n_action_steps
        pos = self.plan_pos[rows]  # >= 1 for a plan under way: its first action ran at its replan
        live = pos < n
        for p in torch.unique(pos[live]).tolist():  # the plans' rests have one length per position
            at = torch.nonzero(live & (pos == p)).flatten()
            rest = unnormalize_action(self.plan[rows[at], p:]).numpy().astype(np.float64)
            safe = self.layer.recheck(view[at.numpy()], rest)
            self.plan_pos[rows[at[torch.from_numpy(~safe)]]] = n

    def _guide(self, view: SafetyView, K: int) -> Callable[[Tensor, Tensor | None], Tensor]:
        """The sampler's clearance guidance for the B = len(view) replanning episodes, K samples each:
        x0 (n, horizon, 2) normalised of the rows ``rows`` (a mask over the B * K samples; None: all)
        -> x0 with its commands from the current step on moved by ``SafetyLayer.clearance_step``; the
        past step is left as sampled."""
        step = self.layer.clearance_step(view, self.settings.guidance)
        sample_of = np.repeat(np.arange(len(view.goal)), K)  # the episode of each of the B * K samples
        first = self.settings.n_obs_steps - 1  # the sample's window starts at the step before the current one

        def guide(x0: Tensor, rows: Tensor | None = None) -> Tensor:
            at = sample_of if rows is None else sample_of[rows.cpu().numpy()]
            moved = step(unnormalize_action(x0[:, first:]).cpu().numpy().astype(np.float64), at)
            out = x0.clone()
            out[:, first:] = normalize_action(torch.from_numpy(moved).to(x0))
            return out

        return guide

    def _guided_proposal(self, view: SafetyView) -> Tensor:
        """Route pursuit's chunk (``SafetyLayer.route_proposal``) moved by the clearance guidance
        ``denoising_steps`` times (as the sampler from noise): the plan of
        ``ReplanExperiment(sampled=False)`` at K = 1 with ``guidance``, normalised
        (B, 1, chunk_length, 2)."""
        proposal = self.layer.route_proposal(view, self.chunk_length)
        step, at = self.layer.clearance_step(view, self.settings.guidance), np.arange(len(view.goal))
        for _ in range(self.settings.denoising_steps):
            proposal = step(proposal, at)
        return normalize_action(torch.from_numpy(proposal).to(self.plan))[:, None]

    def _sample(self, stacked: dict[str, Tensor], noise, warm, view: SafetyView | None) -> Tensor:
        """K candidate chunks (B, K, chunk, A) of the B episodes of ``stacked`` in one sampler call."""
        if self.sampler is None:
            raise ValueError(
                "this replanner has no sampler (ReplanExperiment.sampled=False runs without one)"
            )
        ps, K = self.settings, self.settings.num_candidates
        return self.sampler(
            stacked,
            K,
            noise=noise,
            warm_start=warm,
            warm_start_step=ps.warm_start_step,
            warm_all=True,
            guide=self._guide(view, K) if ps.guidance else None,
        ).to(self.plan.device)  # the plan lives where the observations do (the model may be elsewhere)

    def _replan(self, need: Tensor, view: SafetyView | None, stacked: dict[str, Tensor], noise) -> None:
        ps, ex = self.settings, self.experiment
        K = ps.num_candidates
        if not ex.sampled and not self.best_of:  # route pursuit's chunk, guided
            chunks = self._guided_proposal(view)
        elif not ex.sampled:  # the layer alone: the proposal and the escapes are the candidates
            chunks = self.plan.new_zeros(len(need), 0, *self.plan.shape[1:])
        else:
            warm = None
            if ps.warm_start_step:  # from the unexecuted rest of each episode's last chunk
                guess = warm_start_guess(self.plan[need], self.executed[need], ps.n_obs_steps, ps.horizon)
                warm = (guess, self.has_last[need])
            if callable(noise):  # each episode its own stream, and its own sampler call (``act``)
                noise = noise(need, K)
                parts = []
                for b in range(len(need)):
                    one = slice(b, b + 1)
                    parts.append(
                        self._sample(
                            {k: v[one] if isinstance(v, Tensor) else v for k, v in stacked.items()},
                            noise[b * K : (b + 1) * K],
                            None if warm is None else (warm[0][one], warm[1][one]),
                            None if view is None else view[np.array([b])],
                        )
                    )
                chunks = torch.cat(parts)
            else:
                chunks = self._sample(stacked, noise, warm, view)
        last, has_last = self.last_action[need].to(chunks.dtype), self.has_last[need]
        chunks = smooth_chunks(chunks, last, has_last, ps.chunk_smoothing)  # before best-of-K scores them
        chunks = blend_replan(chunks, last, has_last, ex.blend_steps)
        if self.best_of:
            # the plan being replaced, from now on (normalised), for the layer's coherence preference
            previous = warm_start_guess(self.plan[need], self.executed[need], 1, ps.n_action_steps)
            # a plan the filter cut short met a barrier: nothing to keep to
            keep_to = has_last & (self.executed[need] >= ps.n_action_steps)
            chosen, _ = self.choose(view, chunks, last, has_last, previous, keep_to)
        else:
            chosen = chunks[:, 0]
        self._counts["replans"] += len(need)
        check_finite_chunks(chosen)  # never executed, never a warm start
        self.plan[need] = chosen.to(self.plan.dtype)
        self.plan_pos[need] = 0
        self.executed[need] = 0

    # -- the safety layer's calls on normalised actions ------------------------------------------------
    def choose(
        self,
        view: SafetyView,
        chunks: Tensor,
        last_action: Tensor | None = None,
        has_last=None,
        previous: Tensor | None = None,
        keep_to=None,
    ) -> tuple[Tensor, dict]:
        """``SafetyLayer.choose`` on normalised chunks (B, K, T, 2) (and last actions (B, 2)) -> kept
        chunks (B, T, 2) normalised, info."""
        raw = unnormalize_action(chunks).numpy().astype(np.float64)
        if last_action is not None:
            last_action = unnormalize_action(last_action).numpy().astype(np.float64)
            has_last = has_last.cpu().numpy()
        if previous is not None:
            previous = unnormalize_action(previous).numpy().astype(np.float64)
        if keep_to is not None:
            keep_to = keep_to.cpu().numpy()
        chosen, info = self.layer.choose(
            view, raw, last_action, has_last, previous, keep_to, chunk_smoothing=self.settings.chunk_smoothing
        )
        return normalize_action(torch.from_numpy(chosen)).to(chunks.device, chunks.dtype), info

    def filter(self, view: SafetyView, action: Tensor) -> tuple[Tensor, np.ndarray]:
        """``SafetyLayer.filter`` on normalised actions (B, 2) -> (filtered normalised, changed)."""
        out, changed = self.layer.filter(view, unnormalize_action(action).numpy().astype(np.float64))
        filtered = normalize_action(torch.from_numpy(out).float()).to(action.device, action.dtype)
        return filtered, changed
