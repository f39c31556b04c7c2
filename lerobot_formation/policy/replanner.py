"""The replan loop of a ``formation_diffusion`` policy: the one implementation that ``select_action``
(so ``lerobot-eval``) and the engine's diffusion controller (``bench``) both run.

A ``Replanner`` owns, per episode of a batch, the kept chunk (normalised, the whole predicted horizon
from the step it was planned at), the position of the next action in it, the actions executed since
that replan, the last executed action and the stats. ``act(rows, env_now, history)`` returns the next
action (normalised) of the episodes ``rows``; an episode whose chunk is used up (``n_action_steps``
actions ran), whose last action the filter changed, or (best-of-K) whose kept chunk no longer
passes best-of-K's check on this step's view replans first:

1. warm start (``warm_start_step`` j > 0): the unexecuted rest of the episode's last chunk, shifted to
   the new window and padded with its last action (``warm_start_guess``), is the guess every
   candidate starts from at the sampler's j-th timestep, each with its own noise
   (``FormationDiffusionPolicy.sample_action_chunks``); an episode's first replan samples from pure
   noise;
2. K = ``num_candidates`` candidates in one batched denoiser call; with ``sampling_guidance`` every
   denoising step moves them away from the view's obstacles (``core.guidance``, ``_guide``);
3. blending (``ReplanExperiment.blend_steps``, experiments only): the new chunks' first actions are
   blended from the last executed one (``core.replan_blend``);
4. choice: with K > 1 the one scorer, ``core.safety.select_chunk`` (no predicted contact of the whole
   formation's footprint with the observed obstacles, then cost-to-go progress on a
   ``PROGRESS_RESOLUTION`` grid read bilinearly; escape manoeuvres of ``ESCAPE_SPEEDS`` when nothing
   sampled is safe, else the widest of every candidate scored); with K = 1 the sample. A "nearest+route" policy may add route
   pursuit's chunk from its route hint to the candidates (``safety_route_proposal``; with
   ``safety_proposal_blend`` it enters from the last executed action) and have every
   candidate followed by route pursuit in the check (``safety_route_lookahead``); with
   ``safety_coherence`` the scorer prefers the safe candidate closest to the rest of the plan it
   replaces (``warm_start_guess`` of it from the current step), unless the filter cut that plan short;
5. filter (``safety_filter`` "cbf"): every executed action passes ``core.safety.cbf_filter``; an
   episode whose action it changed replans at its next step (the plan met a barrier);
6. recheck (K > 1): at each step before 1-5, the rest of the kept chunk is
   checked again on the new view with best-of-K's own check (``core.safety.plan_is_safe``, with the
   route lookahead); where it fails, the episode replans at once (a mover's estimated velocity and
   the sensed obstacles change under a chunk in n_action_steps). A chunk kept where nothing was safe
   (the widest fallback) is rechecked like any other, so such an episode replans at every step while
   its rest still fails.

What the scorer and the filter see of an episode at a step is a ``SafetyView``, built once per step
from the raw observation: the goal and obstacles of its ``nearest`` part; with
``safety_moving_obstacles`` their velocities (the encoding's, else the estimates of the episode's
``core.obstacle_tracker.ObstacleTracker``, which takes every step's observation); with a known
actuator (``safety_action_delay``, ``safety_max_linear_accel`` / ``safety_max_angular_accel``)
the ``core.safety.ChunkStart`` after the episode's commands in flight. For that the replanner keeps,
per episode, the last ``safety_action_delay`` commands it sent (physical, clipped to the action
bounds) and the velocity its actuator model executed last (``dynamics.rate_limit`` of the command
that ran, action noise unknown). With a known sensing noise (``safety_obstacle_noise``,
``safety_pose_noise``) the view's obstacles are smoothed over the steps (``core.obstacle_filter``,
carried along with that executed velocity). All of it starts afresh with each episode (``start``).

K, the filter, its margin and rate and the warm start come only from the
policy config the replanner is given (the policy's own, or a copy made with ``dataclasses.replace``
for a bench controller or an ablation row, which runs the config's checks). The settings of the
ablation study that the shipped policy does not use are a ``ReplanExperiment``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from lerobot_formation.core import guidance, safety
from lerobot_formation.core.dynamics import FormationParams, rate_limit
from lerobot_formation.core.obstacle_filter import ObstacleFilter
from lerobot_formation.core.obstacle_grid import get_encoding
from lerobot_formation.core.obstacle_tracker import ObstacleTracker
from lerobot_formation.core.replan_blend import blend_replan, smooth_chunks
from lerobot_formation.core.route_pursuit import pursuit_chunk

# The shipped layer's settings that are no config fields (``FormationDiffusionConfig``'s Args):
ESCAPE_SPEEDS = (0.0, 0.1, 0.2, 0.3, 0.45, 0.6)  # [m/s] best-of-K's escape manoeuvres, each turn rate
PROGRESS_RESOLUTION = 0.4  # [m] the cell of the cost-to-go grid best-of-K reads (bilinearly) progress on
GUIDANCE_DISTANCE = 0.3  # [m] the clearance below which the sampling guidance's cost grows

STAT_KEYS = (
    "replans",
    "replans_none_safe",
    "escapes",
    "stops",
    "steps",
    "filter_interventions",
    "proposals",
    "rechecks_failed",
)


@dataclass(frozen=True)
class ReplanExperiment:
    """Replan settings of the ablation study (``scripts/ablation.py``), not of the shipped policy; the
    defaults are what the policy runs.

    Args:
        blend_steps: m >= 0; a new chunk's first m actions are blended from the last executed action
            (``core.replan_blend``) before best-of-K scores them. 0: plain chunk execution.
        escape_advantage: None: the escape manoeuvres of best-of-K are used only when no sampled chunk
            is safe. A number [m]: a safe manoeuvre is also kept when its cost-to-go progress beats
            every safe sampled chunk's by that much.
        blocked_fallback: "widest" (the sampled chunk with the largest predicted clearance) or "stop"
            when nothing is safe (``core.safety.select_chunk``).
        sampled: False: the network samples nothing; best-of-K's candidates are route pursuit's
            proposal and the escapes, under the same check, filter and recheck. The safety layer
            without the learned planner: the baseline the layer's rows are measured against (needs a
            "nearest+route" config with ``safety_route_proposal``). With K = 1 and
            ``sampling_guidance``, the plan is route pursuit's chunk moved by the sampler's clearance
            guidance ``num_inference_steps`` times (the sampler's steps from noise; its warm-started
            replans run ``warm_start_step`` fewer): the baseline of guided sampling.
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


@functools.cache
def safety_geometry() -> tuple[np.ndarray, float, float]:
    """The formation template (N, 2), dt and agent radius the safety layer assumes: the env's defaults
    (built once: ``FormationParams`` checks the graph's rigidity, ~0.7 ms, at every construction)."""
    params = FormationParams()
    template = np.asarray(params.graph.template)
    template.flags.writeable = False
    return template, params.dt, params.agent_radius


@functools.cache
def _escape_lattice(speeds: tuple[float, ...]) -> np.ndarray:
    """``core.safety.escape_primitives`` of a config's speeds, built once per lattice."""
    lattice = safety.escape_primitives(speeds)
    lattice.flags.writeable = False
    return lattice


@dataclass(frozen=True)
class SafetyView:
    """What the safety layer sees of B episodes at one step (module docstring): goal (B, 2),
    obstacles (B, M, 3) and mask (B, M) in the body frame, the obstacles' velocities (B, M, 2) (None:
    static), where the next command starts (``core.safety.ChunkStart``; None: at once) and the route
    hint's near and far carrots (B, 4) of a "nearest+route" policy (None otherwise)."""

    goal: np.ndarray
    obstacles: np.ndarray
    mask: np.ndarray
    velocity: np.ndarray | None = None
    start: safety.ChunkStart | None = None
    route: np.ndarray | None = None  # (B, 4) the route hint's near and far carrots; None: no hint

    def __getitem__(self, rows) -> SafetyView:
        return SafetyView(
            self.goal[rows],
            self.obstacles[rows],
            self.mask[rows],
            None if self.velocity is None else self.velocity[rows],
            None if self.start is None else self.start[rows],
            None if self.route is None else self.route[rows],
        )


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
    """Per-episode chunks, best-of-K, the filter and replans of one batch of episodes (module docstring).

    Args:
        policy: a ``FormationDiffusionPolicy`` (samples the chunks, holds the action bounds).
        config: the policy config to run (K, filter, margin, warm start); default the policy's own.
        experiment: ablation settings (``ReplanExperiment``); default none.
    """

    def __init__(self, policy, config=None, experiment: ReplanExperiment | None = None):
        self.policy = policy
        self.config = policy.config if config is None else config
        self.experiment = experiment or ReplanExperiment()
        if self.experiment.blend_steps > self.chunk_length:
            raise ValueError(
                f"blend_steps must be in [0, {self.chunk_length}] (the chunk's length), "
                f"got {self.experiment.blend_steps}"
            )
        cfg = self.config
        if not self.experiment.sampled and not (
            cfg.safety_layer and cfg.safety_route_proposal and get_encoding(cfg.obstacle_encoding).map
        ):
            raise ValueError(
                "a replanner that samples nothing (ReplanExperiment.sampled=False) needs route pursuit's "
                "proposal and a safety layer: a route-encoding config with safety_route_proposal and "
                f"num_candidates > 1, a filter or guidance, got obstacle_encoding={cfg.obstacle_encoding!r}, "
                f"safety_route_proposal={cfg.safety_route_proposal}, num_candidates={cfg.num_candidates}, "
                f"safety_filter={cfg.safety_filter!r}, sampling_guidance={cfg.sampling_guidance}"
            )
        self.stats = dict.fromkeys(STAT_KEYS, 0)
        self.plan: Tensor | None = None

    @property
    def chunk_length(self) -> int:
        return self.config.horizon - self.config.n_obs_steps + 1

    def reset(self, batch_size: int | None = None, device: torch.device | str = "cpu") -> None:
        """Forget every episode's plan (and with ``batch_size``, start ``batch_size`` episodes); the stats
        start from zero."""
        self.stats = dict.fromkeys(STAT_KEYS, 0)
        self.plan = None
        if batch_size is not None:
            self.start(batch_size, device)

    def start(self, B: int, device: torch.device | str = "cpu") -> None:
        """Start ``B`` episodes with no plan (each replans at its first ``act``)."""
        A = self.config.action_feature.shape[0]
        self.plan = torch.zeros(B, self.chunk_length, A, device=device)  # normalised, whole chunk
        self.plan_pos = torch.full((B,), self.config.n_action_steps, dtype=torch.long)  # next action
        self.executed = torch.zeros(B, dtype=torch.long)  # actions run since the episode's last replan
        self.last_action = torch.zeros(B, A, device=device)  # normalised
        self.has_last = torch.zeros(B, dtype=torch.bool)
        cfg = self.config
        self.in_flight = np.zeros((B, cfg.safety_action_delay, A))  # sent, not run yet; oldest first
        self.executed_velocity = np.zeros((B, A))  # the actuator model's last executed [v, omega]
        self.tracker = self.smoother = None
        encoding = get_encoding(cfg.obstacle_encoding)
        _, dt, _ = safety_geometry()
        if cfg.safety_layer and cfg.safety_moving_obstacles and not encoding.velocity:
            self.tracker = ObstacleTracker(B, encoding.slots(cfg.max_obstacles), dt)
        if cfg.safety_layer and self.knows_noise:
            self.smoother = ObstacleFilter(
                B,
                encoding.slots(cfg.max_obstacles),
                dt,
                obstacle_noise=cfg.safety_obstacle_noise,
                pose_noise=cfg.safety_pose_noise,
            )

    @property
    def knows_actuator(self) -> bool:
        """Whether the config gives the actuator's delay or rate limits (``SafetyView.start``)."""
        return bool(self.config.safety_action_delay or self.knows_rate_limits)

    @property
    def knows_rate_limits(self) -> bool:
        """Whether the config gives the actuator's rate limits (it then ramps a step in [v, omega])."""
        cfg = self.config
        return cfg.safety_max_linear_accel is not None or cfg.safety_max_angular_accel is not None

    @property
    def agent_radii(self) -> float | np.ndarray:
        """The agent radius the layer checks: one for all four, or with ``safety_follower_margin`` one
        per template agent (N,), the followers' (agents 2 and 3) larger by it; not where the layer
        predicts moving obstacles (``safety_moving_obstacles``), where the team needs its room to get
        out of a mover's way (on level5's tuning scenes 0.03 m cost 21 of 200)."""
        template, _, agent_radius = safety_geometry()
        extra = self.config.safety_follower_margin
        if not extra or self.config.safety_moving_obstacles:
            return agent_radius
        return agent_radius + extra * (np.arange(len(template)) >= 2)  # the first two are the leaders

    @property
    def knows_noise(self) -> bool:
        """Whether the config gives the sensors' noise (then the view is smoothed)."""
        return self.config.safety_obstacle_noise > 0 or self.config.safety_pose_noise > 0

    @property
    def best_of(self) -> bool:
        """Whether replans choose among candidates (K > 1, or no samples: the proposal and escapes,
        except the guided proposal alone of K = 1 with ``sampling_guidance``)."""
        cfg = self.config
        return cfg.num_candidates > 1 or not (self.experiment.sampled or cfg.sampling_guidance)

    def needs_replan(self, rows: Tensor) -> Tensor:
        """Which of ``rows`` replan at their next ``act`` (B,) bool."""
        if self.plan is None:
            return torch.ones(len(rows), dtype=torch.bool)
        return self.plan_pos[rows] >= self.config.n_action_steps

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
        cfg = self.config
        if rows is None:
            rows = torch.arange(len(env_now))
        if self.plan is None:
            self.start(len(rows), env_now.device)
        view = self.view(env_now, rows) if cfg.safety_layer else None
        if self.best_of:
            self._recheck(rows, view)
        need = rows[self.plan_pos[rows] >= cfg.n_action_steps]
        if len(need):
            at = torch.nonzero(self.plan_pos[rows] >= cfg.n_action_steps).flatten()
            self._replan(need, None if view is None else view[at.numpy()], history(need), noise)
        action = self.plan[rows, self.plan_pos[rows]]
        self.plan_pos[rows] += 1
        self.executed[rows] += 1
        self.stats["steps"] += len(rows)
        if cfg.safety_filter == "cbf":
            action, changed = self.filter(view, action)
            self.stats["filter_interventions"] += int(changed.sum())
            # the plan met a barrier: replan at the next step
            self.plan_pos[rows[torch.from_numpy(changed)]] = cfg.n_action_steps
        self.last_action[rows] = action.to(self.last_action.dtype)
        self.has_last[rows] = True
        if view is not None and (self.knows_actuator or self.knows_noise):
            self._send(rows.cpu().numpy(), action)
        return action

    def _recheck(self, rows: Tensor, view: SafetyView) -> None:
        """Best-of-K's recheck: episodes ``rows`` whose plan is under way check its rest on this step's
        ``view`` (``core.safety.plan_is_safe``); those where it fails replan now (a chunk kept where
        nothing was safe, the widest fallback, too: such an episode replans at every step while its
        rest still fails)."""
        cfg = self.config
        pos = self.plan_pos[rows]  # >= 1 for a plan under way: its first action ran at its replan
        live = pos < cfg.n_action_steps
        for p in torch.unique(pos[live]).tolist():  # the plans' rests have one length per position
            at = torch.nonzero(live & (pos == p)).flatten()
            sub = view[at.numpy()]
            rest = self.policy.unnormalize_action(self.plan[rows[at], p:]).numpy().astype(np.float64)
            safe = safety.plan_is_safe(rest, self._check(sub), cfg.safety_margin)
            failed = rows[at[torch.from_numpy(~safe)]]
            self.plan_pos[failed] = cfg.n_action_steps
            self.stats["rechecks_failed"] += len(failed)

    def _check(self, view: SafetyView) -> safety.FootprintCheck:
        """Best-of-K's check (``core.safety.FootprintCheck``) on ``view`` with this config: the
        observed obstacles and velocities, the actuator start, route pursuit's lookahead."""
        template, dt, _ = safety_geometry()
        return safety.FootprintCheck(
            view.obstacles,
            template,
            dt,
            self.agent_radii,
            view.velocity,
            view.start,
            self._continuation(view),
            self.config.safety_mover_uncertainty,
        )

    def _continuation(self, view: SafetyView) -> Callable[[np.ndarray], np.ndarray] | None:
        """What best-of-K assumes the team runs after a sequence: route pursuit for
        ``safety_route_lookahead`` steps from each end pose (B, P, 3) -> (B, P, n, 2); None without."""
        cfg = self.config
        if not cfg.safety_route_lookahead:
            return None
        _, dt, _ = safety_geometry()

        def continuation(end: np.ndarray) -> np.ndarray:
            B, P = end.shape[:2]
            n = cfg.safety_route_lookahead
            route, goal = np.repeat(view.route, P, axis=0), np.repeat(view.goal, P, axis=0)
            out = pursuit_chunk(route, goal, n, dt, cfg.action_high[1], start=end.reshape(B * P, 3))
            return out.reshape(B, P, n, 2)

        return continuation

    def _clearance_step(self, view: SafetyView) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        """One application of the clearance guidance (``sampling_guidance``) to commands of the
        B = len(view) replanning episodes: (commands (n, T, 2) [m/s, rad/s] from the current step on,
        the episode of each row (n,)) -> the commands moved by one step of -eta dJ/da
        (``core.guidance.clearance_cost_gradient``, on the view's obstacles from the actuator's
        predicted start), each clipped to the action bounds."""
        cfg = self.config
        template, dt, _ = safety_geometry()
        pose, steps = safety.chunk_origin(view.start, len(view.goal))
        velocity = view.velocity  # None unless the layer predicts moving obstacles
        low, high = np.asarray(cfg.action_low), np.asarray(cfg.action_high)

        def step(moved: np.ndarray, at: np.ndarray) -> np.ndarray:
            _, grad = guidance.clearance_cost_gradient(
                pose[at],
                moved[:, None],
                view.obstacles[at],
                template,
                dt,
                self.agent_radii,
                GUIDANCE_DISTANCE,
                None if velocity is None else velocity[at],
                steps,
            )
            return np.clip(moved - cfg.sampling_guidance * grad[:, 0], low, high)

        return step

    def _guide(self, view: SafetyView, K: int) -> Callable[[Tensor, Tensor | None], Tensor]:
        """The sampler's clearance guidance for the B = len(view) replanning episodes, K samples each:
        x0 (n, horizon, 2) normalised of the rows ``rows`` (a mask over the B * K samples; None: all)
        -> x0 with its commands from the current step on moved by ``_clearance_step``; the past step
        is left as sampled."""
        step = self._clearance_step(view)
        sample_of = np.repeat(np.arange(len(view.goal)), K)  # the episode of each of the B * K samples
        first = self.config.n_obs_steps - 1  # the sample's window starts at the step before the current one

        def guide(x0: Tensor, rows: Tensor | None = None) -> Tensor:
            at = sample_of if rows is None else sample_of[rows.cpu().numpy()]
            moved = step(self.policy.unnormalize_action(x0[:, first:]).cpu().numpy().astype(np.float64), at)
            out = x0.clone()
            out[:, first:] = self.policy.normalize_action(torch.from_numpy(moved).to(x0))
            return out

        return guide

    def _guided_proposal(self, view: SafetyView) -> Tensor:
        """Route pursuit's chunk (``pursuit_chunk`` of the view's route hint) moved by the clearance
        guidance ``num_inference_steps`` times (as the sampler from noise; warm-started, it runs
        ``warm_start_step`` fewer guided steps): the plan of
        ``ReplanExperiment(sampled=False)`` at K = 1 with ``sampling_guidance``, normalised
        (B, 1, chunk_length, 2)."""
        cfg = self.config
        _, dt, _ = safety_geometry()
        proposal = pursuit_chunk(view.route, view.goal, self.chunk_length, dt, cfg.action_high[1])
        step, at = self._clearance_step(view), np.arange(len(view.goal))
        for _ in range(cfg.num_inference_steps or cfg.num_train_timesteps):
            proposal = step(proposal, at)
        return self.policy.normalize_action(torch.from_numpy(proposal).to(self.plan))[:, None]

    def _send(self, rows: np.ndarray, action: Tensor) -> None:
        """Record the commands (normalised) sent to episodes ``rows``: the actuator model runs the
        oldest in flight (or this one, without a delay) and queues this one."""
        cfg = self.config
        sent = np.clip(
            self.policy.unnormalize_action(action).numpy().astype(np.float64), cfg.action_low, cfg.action_high
        )
        runs = sent
        if cfg.safety_action_delay:
            runs = self.in_flight[rows, 0]
            self.in_flight[rows, :-1] = self.in_flight[rows, 1:]
            self.in_flight[rows, -1] = sent
        _, dt, _ = safety_geometry()
        self.executed_velocity[rows] = rate_limit(
            self.executed_velocity[rows], runs, cfg.safety_max_linear_accel, cfg.safety_max_angular_accel, dt
        )

    def _sample(self, stacked: dict[str, Tensor], noise, warm, view: SafetyView | None) -> Tensor:
        """K candidate chunks (B, K, chunk, A) of the B episodes of ``stacked`` in one sampler call."""
        cfg = self.config
        return self.policy.sample_action_chunks(
            stacked,
            cfg.num_candidates,
            noise=noise,
            warm_start=warm,
            warm_start_step=cfg.warm_start_step,
            warm_all=True,
            guide=self._guide(view, cfg.num_candidates) if cfg.sampling_guidance else None,
        ).to(self.plan.device)  # the plan lives where the observations do (the model may be elsewhere)

    def _replan(self, need: Tensor, view: SafetyView | None, stacked: dict[str, Tensor], noise) -> None:
        cfg, ex = self.config, self.experiment
        K = cfg.num_candidates
        if not ex.sampled and not self.best_of:  # route pursuit's chunk, guided
            chunks = self._guided_proposal(view)
        elif not ex.sampled:  # the layer alone: the proposal and the escapes are the candidates
            chunks = self.plan.new_zeros(len(need), 0, *self.plan.shape[1:])
        else:
            warm = None
            if cfg.warm_start_step:  # from the unexecuted rest of each episode's last chunk
                guess = warm_start_guess(self.plan[need], self.executed[need], cfg.n_obs_steps, cfg.horizon)
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
        chunks = smooth_chunks(chunks, last, has_last, cfg.chunk_smoothing)  # before best-of-K scores them
        chunks = blend_replan(chunks, last, has_last, ex.blend_steps)
        if self.best_of:
            previous, keep_to = None, None
            if cfg.safety_coherence:  # the plan being replaced, from now on (normalised)
                previous = warm_start_guess(self.plan[need], self.executed[need], 1, cfg.n_action_steps)
                # a plan the filter cut short met a barrier: nothing to keep to
                keep_to = has_last & (self.executed[need] >= cfg.n_action_steps)
            chosen, info = self.choose(view, chunks, last, has_last, previous, keep_to)
            self.stats["replans_none_safe"] += int((~info["any_safe"]).sum())
            self.stats["escapes"] += int(info["escaped"].sum())
            self.stats["stops"] += int(info["stopped"].sum())
            self.stats["proposals"] += int(info["proposal_kept"].sum())
        else:
            chosen = chunks[:, 0]
        self.stats["replans"] += len(need)
        check_finite_chunks(chosen)  # never executed, never a warm start
        self.plan[need] = chosen.to(self.plan.dtype)
        self.plan_pos[need] = 0
        self.executed[need] = 0

    # -- the safety layer: the one scorer and the filter, on physical actions ------------------------
    def observed_obstacles(self, env_state) -> SafetyView:
        """Goal (B, 2), obstacles (B, M, 3) and mask (B, M) in the body frame from a raw egocentric
        observation (B, D), and with ``safety_moving_obstacles`` the velocities an encoding that
        observes them gives (``nearest+velocity``: after the rows); no tracker, no actuator."""
        cfg = self.config
        encoding = get_encoding(cfg.obstacle_encoding)
        slots = encoding.slots(cfg.max_obstacles)
        env = env_state.float().cpu().numpy() if isinstance(env_state, Tensor) else np.asarray(env_state)
        rows_end = encoding.fixed + encoding.per_slot * slots
        # the nearest part only (e.g. "nearest+route" adds a route hint, "nearest+velocity" velocities)
        goal, obstacles, mask = safety.decode_nearest(env[:, :rows_end], slots)
        velocity = None
        if cfg.safety_moving_obstacles and encoding.velocity:
            velocity = env[:, rows_end : rows_end + 2 * slots].reshape(len(env), slots, 2).astype(np.float64)
            velocity = np.where(mask[..., None], velocity, 0.0)
        route = None
        if encoding.map:  # the route hint's carrots, after the velocities (core.route_encoding)
            at = rows_end + encoding.trailing_per_slot * slots
            route = env[:, at : at + 4].astype(np.float64)
        return SafetyView(goal, obstacles, mask, velocity, route=route)

    def view(self, env_state: Tensor, rows: Tensor) -> SafetyView:
        """The ``SafetyView`` of episodes ``rows`` at this step from their raw observation (len(rows),
        D); updates their obstacle trackers (call it once per step)."""
        view = self.observed_obstacles(env_state)
        cfg = self.config
        velocity, start = view.velocity, None
        idx = rows.cpu().numpy()
        if self.tracker is not None:
            velocity = self.tracker.update(view.goal, view.obstacles, view.mask, idx)
        obstacles = view.obstacles
        if self.smoother is not None:  # carried along with the velocity the team executed last step
            obstacles = self.smoother.update(obstacles, view.mask, self.executed_velocity[idx], velocity, idx)
        if self.knows_actuator:
            _, dt, _ = safety_geometry()
            start = safety.predict_start(
                self.in_flight[idx],
                self.executed_velocity[idx],
                dt,
                cfg.safety_max_linear_accel,
                cfg.safety_max_angular_accel,
            )
        return SafetyView(view.goal, obstacles, view.mask, velocity, start, view.route)

    def _as_view(self, seen) -> SafetyView:
        return seen if isinstance(seen, SafetyView) else self.observed_obstacles(seen)

    def choose_raw(
        self,
        seen,
        chunks: np.ndarray,
        last_action: np.ndarray | None = None,
        has_last=None,
        previous: np.ndarray | None = None,
        keep_to=None,
    ) -> tuple[np.ndarray, dict]:
        """Best-of-K (``core.safety.select_chunk``) with this config: ``seen`` a ``SafetyView`` or a raw
        egocentric observation (B, D) (``observed_obstacles``), chunks (B, K, T, 2) in m/s and rad/s
        -> kept chunks (B, T, 2), info. With blending and the last executed actions (B, 2) [m/s,
        rad/s], the escape manoeuvres are blended into them as the sampled chunks were, and with
        ``safety_proposal_blend`` route pursuit's proposal (where ``has_last``, default everywhere),
        then smoothed as the sampled chunks are (``chunk_smoothing``). ``previous``
        (B, n, 2) [m/s, rad/s]: the plan being replaced, from now on, kept to where ``keep_to`` (B,)
        (default: everywhere) by the ``safety_coherence`` preference; None: no such preference."""
        view = self._as_view(seen)
        template, dt, _ = safety_geometry()
        agent_radius = self.agent_radii
        cfg, ex = self.config, self.experiment
        blend = None
        if last_action is not None and ex.blend_steps:
            blend = (np.asarray(last_action), np.asarray(has_last), ex.blend_steps)
        K = chunks.shape[1]
        if cfg.safety_route_proposal:  # route pursuit's chunk competes with the sampled ones
            proposal = pursuit_chunk(view.route, view.goal, chunks.shape[2], dt, cfg.action_high[1])
            if cfg.safety_proposal_blend and last_action is not None and not self.knows_rate_limits:
                # enter from the running command (a rate-limited actuator ramps the step by itself)
                had = np.ones(len(proposal), bool) if has_last is None else np.asarray(has_last)
                last = np.asarray(last_action)
                proposal = blend_replan(proposal, last, had, cfg.safety_proposal_blend)
                proposal = smooth_chunks(proposal, last, had, cfg.chunk_smoothing)
            chunks = np.concatenate([chunks, proposal[:, None]], axis=1)
        coherence = None
        if previous is not None and cfg.safety_coherence:
            coherence = safety.PlanCoherence(
                np.asarray(previous),
                np.ones(len(chunks), bool) if keep_to is None else np.asarray(keep_to),
                np.asarray(cfg.action_high) - np.asarray(cfg.action_low),
                cfg.safety_coherence,
            )
        chosen, info = safety.select_chunk(
            chunks,
            view.obstacles,
            view.goal,
            template,
            dt,
            agent_radius,
            self.config.safety_margin,
            escape_advantage=ex.escape_advantage,
            blend=blend,
            blocked_fallback=ex.blocked_fallback,
            obstacle_velocity=view.velocity,
            start=view.start,
            continuation=self._continuation(view),
            coherence=coherence,
            progress_resolution=PROGRESS_RESOLUTION,
            progress_bilinear=True,
            primitives=_escape_lattice(ESCAPE_SPEEDS),
            mover_uncertainty=cfg.safety_mover_uncertainty,
            halt_lookahead=cfg.safety_halt_lookahead if cfg.safety_moving_obstacles else 0,
            fallback_all=True,
        )
        info["proposal_kept"] = (
            info["choice"] == K if cfg.safety_route_proposal else np.zeros(len(chosen), bool)
        )
        return chosen, info

    def choose(
        self,
        view: SafetyView,
        chunks: Tensor,
        last_action: Tensor | None = None,
        has_last=None,
        previous: Tensor | None = None,
        keep_to=None,
    ) -> tuple[Tensor, dict]:
        """``choose_raw`` on normalised chunks (B, K, T, 2) (and last actions (B, 2)) -> kept chunks
        (B, T, 2) normalised."""
        policy = self.policy
        raw = policy.unnormalize_action(chunks).numpy().astype(np.float64)
        if last_action is not None:
            last_action = policy.unnormalize_action(last_action).numpy().astype(np.float64)
            has_last = has_last.cpu().numpy()
        if previous is not None:
            previous = policy.unnormalize_action(previous).numpy().astype(np.float64)
        if keep_to is not None:
            keep_to = keep_to.cpu().numpy()
        chosen, info = self.choose_raw(view, raw, last_action, has_last, previous, keep_to)
        return policy.normalize_action(torch.from_numpy(chosen)).to(chunks.device, chunks.dtype), info

    def filter_raw(self, seen, action: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """CBF filter (``core.safety.cbf_filter``) with this config on [v, omega] (B, 2) -> (filtered,
        changed); ``seen`` as in ``choose_raw``."""
        view = self._as_view(seen)
        template, dt, _ = safety_geometry()
        agent_radius = self.agent_radii
        cfg = self.config
        return safety.cbf_filter(
            action,
            view.obstacles,
            template,
            agent_radius,
            cfg.safety_margin,
            cfg.cbf_rate,
            np.asarray(cfg.action_low),
            np.asarray(cfg.action_high),
            obstacle_velocity=view.velocity,
            start=view.start,
            dt=dt,
        )

    def filter(self, view: SafetyView, action: Tensor) -> tuple[Tensor, np.ndarray]:
        """``filter_raw`` on normalised actions (B, 2) -> (filtered normalised, changed)."""
        policy = self.policy
        out, changed = self.filter_raw(view, policy.unnormalize_action(action).numpy().astype(np.float64))
        filtered = policy.normalize_action(torch.from_numpy(out).float()).to(action.device, action.dtype)
        return filtered, changed
