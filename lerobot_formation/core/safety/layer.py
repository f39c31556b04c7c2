"""The safety layer as one unit: its settings (``SafetySettings``), what it sees of an episode at a
step (``SafetyView``) and the layer itself (``SafetyLayer``), NumPy only.

The layer sits between a planner's proposals and the robot. It takes numpy arrays in physical units
([v, omega] in m/s and rad/s, the body frame of ``core.safety.filters``) and owns, per episode of a batch,
what it must remember between steps: the commands in flight and the velocity the actuator model
executed last, the obstacle tracker (velocities) and the obstacle filter (sensing noise). Its calls:

- ``view(env_state, rows)``: what the layer sees of episodes ``rows`` at this step, from their raw
  egocentric observation (``observed_obstacles`` decodes it): the goal and obstacles of its
  ``nearest`` part; with ``moving_obstacles`` their velocities (the encoding's, else the episode's
  ``core.perception.obstacle_tracker.ObstacleTracker`` estimates); with a known actuator (``action_delay``,
  ``max_linear_accel`` / ``max_angular_accel``) the ``core.safety.filters.ChunkStart`` after the commands
  in flight; with a known sensing noise (``obstacle_noise``, ``pose_noise``) the obstacles smoothed
  over the steps (``core.perception.obstacle_filter``). Call it once per step.
- ``choose(view, chunks)``: best-of-K (``core.safety.filters.select_chunk``) among candidate chunks
  (B, K, T, 2): with ``route_proposal`` route pursuit's chunk joins them, with ``route_lookahead``
  every candidate is followed by route pursuit in the check, with ``coherence`` the layer prefers
  the safe candidate closest to the plan it replaces; escape manoeuvres of ``ESCAPE_SPEEDS`` where
  nothing is safe, else the widest of every candidate scored; progress on a ``PROGRESS_RESOLUTION``
  grid read bilinearly.
- ``recheck(view, plans)``: whether the rest of each kept plan still passes best-of-K's check on
  this step's view (``core.safety.filters.plan_is_safe``).
- ``filter(view, action)``: the filter on every executed action (``filter`` "cbf":
  ``core.safety.filters.cbf_filter``).
- ``send(rows, commands)``: the commands sent to episodes ``rows``, for the actuator model.
- ``clearance_step(view)``: one step of the sampler's clearance guidance (``guidance``,
  ``core.safety.guidance``) on the view's obstacles.

``stats`` counts what the layer did since ``reset`` (``LAYER_STAT_KEYS``): the replans where no
sampled candidate was safe, the escapes and stops kept, route pursuit's proposal kept, the failed
rechecks and the filter's interventions. The policy's ``Replanner`` (``policy/replanner.py``)
calls the layer with the normalised chunks of its sampler converted to physical units; the bench's
``route-pursuit-safe`` runs the same layer with no network at all.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields

import numpy as np

from lerobot_formation.core.controllers.footprint import TeamBody
from lerobot_formation.core.controllers.route_pursuit import pursuit_chunk
from lerobot_formation.core.encodings.obstacle_grid import get_encoding
from lerobot_formation.core.perception.obstacle_filter import ObstacleFilter
from lerobot_formation.core.perception.obstacle_tracker import ObstacleTracker
from lerobot_formation.core.safety import filters as safety
from lerobot_formation.core.safety import guidance
from lerobot_formation.core.safety.replan_blend import blend_replan, smooth_chunks
from lerobot_formation.core.world.dynamics import FormationParams, rate_limit

# The shipped layer's settings that are no settings field:
ESCAPE_SPEEDS = (0.0, 0.1, 0.2, 0.3, 0.45, 0.6)  # [m/s] best-of-K's escape manoeuvres, each turn rate
PROGRESS_RESOLUTION = 0.4  # [m] the cell of the cost-to-go grid best-of-K reads (bilinearly) progress on
GUIDANCE_DISTANCE = 0.3  # [m] the clearance below which the sampling guidance's cost grows
FILTERS = ("none", "cbf")  # the per-action filters (``SafetySettings.filter``)

# What ``SafetyLayer.stats`` counts (module docstring).
LAYER_STAT_KEYS = (
    "replans_none_safe",
    "escapes",
    "stops",
    "filter_interventions",
    "proposals",
    "rechecks_failed",
)


def _config(name: str):
    """A settings field's metadata: the policy config field it is read from (``from_config``)."""
    return {"config": name}


@dataclass(frozen=True)
class SafetySettings:
    """Everything the safety layer is told, in one value. The defaults are the shipped default's (a
    ``FormationDiffusionConfig()``'s); each field is read from one policy config field
    (``from_config``; the name in brackets), whose docstring describes it.

    Attributes:
        filter: the filter on every executed action, "none" or "cbf" (``safety_filter``).
        margin: [m] the clearance kept between every agent disc and every obstacle (``safety_margin``).
        follower_margin: [m] the followers' clearance on top of it, not where the layer predicts
            moving obstacles (``safety_follower_margin``).
        cbf_rate: the barrier's decay rate alpha [1/s] (``cbf_rate``).
        moving_obstacles: predict the observed obstacles at constant velocity
            (``safety_moving_obstacles``).
        mover_uncertainty: [m/s] the growth of a moving obstacle's predicted radius per second ahead
            (``safety_mover_uncertainty``).
        action_delay: [control steps] the actuator's known delay (``safety_action_delay``).
        max_linear_accel: [m/s^2] the actuator's known limit on dv/dt, None: none
            (``safety_max_linear_accel``).
        max_angular_accel: [rad/s^2] the same on domega/dt (``safety_max_angular_accel``).
        obstacle_noise: [m] the known std of the observed obstacles' noise (``safety_obstacle_noise``).
        pose_noise: [m, rad] the known std of the observed pose's noise (``safety_pose_noise``).
        route_proposal: route pursuit's chunk joins the candidates (``safety_route_proposal``).
        route_lookahead: [steps] route pursuit after every candidate in the check
            (``safety_route_lookahead``).
        halt_lookahead: [steps] where nothing passes with its lookahead, prefer the candidates after
            which a braking team stays clear of the movers this long (``safety_halt_lookahead``).
        proposal_blend: [steps] route pursuit's proposal enters from the command being executed
            (``safety_proposal_blend``).
        coherence: [m] best-of-K's weight on keeping to the plan it replaces (``safety_coherence``).
        chunk_smoothing: [passes] of the [1, 2, 1] / 4 kernel over every sampled chunk and the
            blended proposal (``chunk_smoothing``).
        guidance: eta, the step of the sampler's clearance guidance; 0: none (``sampling_guidance``).
        obstacle_encoding: the observation's layout the layer decodes (``obstacle_encoding``).
        max_obstacles: its obstacle slots, None: the encoding's default (``max_obstacles``).
    """

    filter: str = field(default="cbf", metadata=_config("safety_filter"))
    margin: float = field(default=0.05, metadata=_config("safety_margin"))
    follower_margin: float = field(default=0.03, metadata=_config("safety_follower_margin"))
    cbf_rate: float = field(default=4.0, metadata=_config("cbf_rate"))
    moving_obstacles: bool = field(default=False, metadata=_config("safety_moving_obstacles"))
    mover_uncertainty: float = field(default=0.1, metadata=_config("safety_mover_uncertainty"))
    action_delay: int = field(default=0, metadata=_config("safety_action_delay"))
    max_linear_accel: float | None = field(default=None, metadata=_config("safety_max_linear_accel"))
    max_angular_accel: float | None = field(default=None, metadata=_config("safety_max_angular_accel"))
    obstacle_noise: float = field(default=0.0, metadata=_config("safety_obstacle_noise"))
    pose_noise: float = field(default=0.0, metadata=_config("safety_pose_noise"))
    route_proposal: bool = field(default=True, metadata=_config("safety_route_proposal"))
    route_lookahead: int = field(default=20, metadata=_config("safety_route_lookahead"))
    halt_lookahead: int = field(default=20, metadata=_config("safety_halt_lookahead"))
    proposal_blend: int = field(default=4, metadata=_config("safety_proposal_blend"))
    coherence: float = field(default=1.0, metadata=_config("safety_coherence"))
    chunk_smoothing: int = field(default=2, metadata=_config("chunk_smoothing"))
    guidance: float = field(default=1.0, metadata=_config("sampling_guidance"))
    obstacle_encoding: str = field(default="nearest+route", metadata=_config("obstacle_encoding"))
    max_obstacles: int | None = field(default=None, metadata=_config("max_obstacles"))

    def __post_init__(self):
        def refuse(name: str, want: str) -> None:
            value = getattr(self, name)
            raise ValueError(f"{name} ({CONFIG_FIELDS[name]}) must be {want}, got {value!r}")

        if self.filter not in FILTERS:
            refuse("filter", f"one of {FILTERS}")
        for name in (
            "margin",
            "follower_margin",
            "mover_uncertainty",
            "obstacle_noise",
            "pose_noise",
            "coherence",
            "guidance",
        ):
            if not _finite_at_least(getattr(self, name), 0.0):
                refuse(name, "a finite number >= 0")
        if not (_finite_at_least(self.cbf_rate, 0.0) and self.cbf_rate > 0):
            refuse("cbf_rate", "a finite number > 0")
        for name in (
            "action_delay",
            "route_lookahead",
            "halt_lookahead",
            "proposal_blend",
            "chunk_smoothing",
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, int) and value >= 0):
                refuse(name, "an integer >= 0")
        for name in ("max_linear_accel", "max_angular_accel"):
            value = getattr(self, name)
            if value is not None and not (_finite_at_least(value, 0.0) and value > 0):
                refuse(name, "None (no limit) or a number > 0")

    @classmethod
    def from_config(cls, config) -> SafetySettings:
        """The settings a policy config (``FormationDiffusionConfig``, or any object with its field
        names) gives the layer: each field from its config field (``CONFIG_FIELDS``)."""
        return cls(**{name: getattr(config, source) for name, source in CONFIG_FIELDS.items()})

    @staticmethod
    def config_fields(**settings) -> dict:
        """The policy config fields (name -> value) of settings given by their names here, e.g.
        ``config_fields(margin=0.1)`` -> ``{"safety_margin": 0.1}``; an unknown name is refused."""
        unknown = sorted(set(settings) - set(CONFIG_FIELDS))
        if unknown:
            raise ValueError(f"unknown safety settings {unknown}; choose from {sorted(CONFIG_FIELDS)}")
        return {CONFIG_FIELDS[name]: value for name, value in settings.items()}

    @staticmethod
    def from_config_fields(values: dict) -> dict:
        """The inverse of ``config_fields``: settings (name -> value) of the policy config fields among
        ``values`` (the others are left out)."""
        return {name: values[source] for name, source in CONFIG_FIELDS.items() if source in values}


def _finite_at_least(value, low: float) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, float)) and low <= value < math.inf


# settings field -> the policy config field it is read from (``SafetySettings.from_config``)
CONFIG_FIELDS: dict[str, str] = {f.name: f.metadata["config"] for f in fields(SafetySettings)}


def known_world(conditions, scenes_move: bool = False) -> dict:
    """The settings (name -> value) of the layer's knowledge of a run under ``conditions``
    (``core.perception.conditions.Conditions`` or None): the actuator's delay and acceleration limits, the
    sensors' noise stds, and whether obstacles move: ``moving_obstacles`` of the conditions, or
    ``scenes_move`` (the scenes give their obstacles' velocities). What a robot's designer knows of
    the world, never its noise draws. Empty when neither conditions nor moving scenes."""
    known = {}
    if conditions is not None and conditions.enabled:
        known = {
            "action_delay": conditions.action_delay,
            "max_linear_accel": conditions.max_linear_accel,
            "max_angular_accel": conditions.max_angular_accel,
            "obstacle_noise": conditions.obstacle_noise,
            "pose_noise": conditions.pose_noise,
            "moving_obstacles": conditions.moving_obstacles > 0,
        }
    if scenes_move:
        known["moving_obstacles"] = True
    return known


@functools.cache
def safety_geometry() -> tuple[np.ndarray, float, float]:
    """The formation template (N, 2), dt and agent radius the safety layer assumes: the env's defaults
    (built once: ``FormationParams`` checks the graph's rigidity, ~0.7 ms, at every construction)."""
    params = FormationParams()
    template = np.asarray(params.graph.template)
    template.flags.writeable = False
    return template, params.dt, params.agent_radius


@functools.cache
def action_bounds() -> tuple[tuple[float, float], tuple[float, float]]:
    """The env's action bounds ([v, omega] low, high): v in [0, v_max], omega in [-omega_max,
    omega_max] (``FormationParams``), what the layer clips to and a policy normalises with."""
    params = FormationParams()
    return (0.0, -params.omega_max), (params.v_max, params.omega_max)


@functools.cache
def _escape_lattice(speeds: tuple[float, ...]) -> np.ndarray:
    """``core.safety.filters.escape_primitives`` of a lattice's speeds, built once per lattice."""
    lattice = safety.escape_primitives(speeds)
    lattice.flags.writeable = False
    return lattice


@dataclass(frozen=True)
class SafetyView:
    """What the safety layer sees of B episodes at one step (module docstring): goal (B, 2),
    obstacles (B, M, 3) and mask (B, M) in the body frame, the obstacles' velocities (B, M, 2) (None:
    static), where the next command starts (``core.safety.filters.ChunkStart``; None: at once) and the route
    hint's near and far carrots (B, 4) of a route encoding (None otherwise)."""

    goal: np.ndarray
    obstacles: np.ndarray
    mask: np.ndarray
    velocity: np.ndarray | None = None
    start: safety.ChunkStart | None = None
    route: np.ndarray | None = None

    def __getitem__(self, rows) -> SafetyView:
        return SafetyView(
            self.goal[rows],
            self.obstacles[rows],
            self.mask[rows],
            None if self.velocity is None else self.velocity[rows],
            None if self.start is None else self.start[rows],
            None if self.route is None else self.route[rows],
        )


class SafetyLayer:
    """The safety layer of B episodes (module docstring), in physical units.

    Args:
        settings: what it is told (default: the shipped default's, ``SafetySettings()``).
        blend_steps: m >= 0; where the caller blended its chunks' first m actions from the last
            executed one (``core.safety.replan_blend``), the escape manoeuvres are blended as they were.
        escape_advantage: None, or [m] a safe manoeuvre is also kept when its progress beats every safe
            sampled chunk's by that much (``core.safety.filters.select_chunk``).
        blocked_fallback: "widest" or "stop" where nothing is safe (``core.safety.filters.select_chunk``).

    Its checks move ``body`` (``core.controllers.footprint.TeamBody``): ``safety_geometry``'s template
    and step with the layer's ``agent_radii``.
    """

    def __init__(
        self,
        settings: SafetySettings | None = None,
        *,
        blend_steps: int = 0,
        escape_advantage: float | None = None,
        blocked_fallback: str = "widest",
    ):
        self.settings = SafetySettings() if settings is None else settings
        self.blend_steps = blend_steps
        self.escape_advantage = escape_advantage
        self.blocked_fallback = blocked_fallback
        self.encoding = get_encoding(self.settings.obstacle_encoding)
        self.slots = self.encoding.slots(self.settings.max_obstacles)
        template, dt, _ = safety_geometry()
        self.body = TeamBody(template, self.agent_radii, dt)  # the team every check moves
        self.stats = dict.fromkeys(LAYER_STAT_KEYS, 0)
        self.in_flight: np.ndarray | None = None
        self.executed_velocity: np.ndarray | None = None
        self.tracker: ObstacleTracker | None = None
        self.smoother: ObstacleFilter | None = None

    # -- per-episode state ---------------------------------------------------------------------------
    def reset(self, batch_size: int | None = None) -> None:
        """The counts start from zero (and with ``batch_size``, ``batch_size`` episodes start)."""
        self.stats = dict.fromkeys(LAYER_STAT_KEYS, 0)
        if batch_size is not None:
            self.start(batch_size)

    def start(self, B: int) -> None:
        """Start ``B`` episodes: nothing in flight, at rest, new tracks."""
        s = self.settings
        _, dt, _ = safety_geometry()
        self.in_flight = np.zeros((B, s.action_delay, 2))  # sent, not run yet; oldest first
        self.executed_velocity = np.zeros((B, 2))  # the actuator model's last executed [v, omega]
        self.tracker = self.smoother = None
        if s.moving_obstacles and not self.encoding.velocity:
            self.tracker = ObstacleTracker(B, self.slots, dt)
        if self.knows_noise:
            self.smoother = ObstacleFilter(
                B, self.slots, dt, obstacle_noise=s.obstacle_noise, pose_noise=s.pose_noise
            )

    @property
    def knows_actuator(self) -> bool:
        """Whether the layer knows the actuator's delay or rate limits (``SafetyView.start``)."""
        return bool(self.settings.action_delay or self.knows_rate_limits)

    @property
    def knows_rate_limits(self) -> bool:
        """Whether the layer knows the actuator's rate limits (it then ramps a step in [v, omega])."""
        s = self.settings
        return s.max_linear_accel is not None or s.max_angular_accel is not None

    @property
    def knows_noise(self) -> bool:
        """Whether the layer knows the sensors' noise (then the view is smoothed)."""
        return self.settings.obstacle_noise > 0 or self.settings.pose_noise > 0

    @property
    def tracks_commands(self) -> bool:
        """Whether the layer needs the commands sent (``send``): for the actuator model or the
        smoothing's motion."""
        return self.knows_actuator or self.knows_noise

    @property
    def agent_radii(self) -> float | np.ndarray:
        """The agent radius the layer checks: one for all four, or with ``follower_margin`` one per
        template agent (N,), the followers' (agents 2 and 3) larger by it; not where the layer
        predicts moving obstacles (``moving_obstacles``), where the team needs its room to get out of
        a mover's way (on level5's tuning scenes 0.03 m cost 21 of 200)."""
        template, _, agent_radius = safety_geometry()
        extra = self.settings.follower_margin
        if not extra or self.settings.moving_obstacles:
            return agent_radius
        return agent_radius + extra * (np.arange(len(template)) >= 2)  # the first two are the leaders

    # -- what the layer sees -------------------------------------------------------------------------
    def observed_obstacles(self, env_state: np.ndarray) -> SafetyView:
        """Goal (B, 2), obstacles (B, M, 3) and mask (B, M) in the body frame from a raw egocentric
        observation (B, D), and with ``moving_obstacles`` the velocities an encoding that observes
        them gives (``nearest+velocity``: after the rows), and a route encoding's carrots; no
        tracker, no actuator."""
        encoding, slots = self.encoding, self.slots
        env = np.asarray(env_state)
        rows_end = encoding.fixed + encoding.per_slot * slots
        # the nearest part only (e.g. "nearest+route" adds a route hint, "nearest+velocity" velocities)
        goal, obstacles, mask = safety.decode_nearest(env[:, :rows_end], slots)
        velocity = None
        if self.settings.moving_obstacles and encoding.velocity:
            velocity = env[:, rows_end : rows_end + 2 * slots].reshape(len(env), slots, 2).astype(np.float64)
            velocity = np.where(mask[..., None], velocity, 0.0)
        route = None
        if encoding.map:  # the route hint's carrots, after the velocities (core.encodings.route_encoding)
            at = rows_end + encoding.trailing_per_slot * slots
            route = env[:, at : at + 4].astype(np.float64)
        return SafetyView(goal, obstacles, mask, velocity, route=route)

    def view(self, env_state: np.ndarray, rows: np.ndarray) -> SafetyView:
        """The ``SafetyView`` of episodes ``rows`` (indices into the batch) at this step from their raw
        observation (len(rows), D); updates their obstacle trackers and filters (call it once per
        step)."""
        view = self.observed_obstacles(env_state)
        s = self.settings
        velocity, start = view.velocity, None
        idx = np.asarray(rows)
        if self.tracker is not None:
            velocity = self.tracker.update(view.goal, view.obstacles, view.mask, idx)
        obstacles = view.obstacles
        if self.smoother is not None:  # carried along with the velocity the team executed last step
            obstacles = self.smoother.update(obstacles, view.mask, self.executed_velocity[idx], velocity, idx)
        if self.knows_actuator:
            _, dt, _ = safety_geometry()
            start = safety.predict_start(
                self.in_flight[idx], self.executed_velocity[idx], dt, s.max_linear_accel, s.max_angular_accel
            )
        return SafetyView(view.goal, obstacles, view.mask, velocity, start, view.route)

    def _as_view(self, seen) -> SafetyView:
        return seen if isinstance(seen, SafetyView) else self.observed_obstacles(seen)

    # -- best-of-K and its recheck -------------------------------------------------------------------
    def route_proposal(self, view: SafetyView, steps: int) -> np.ndarray:
        """Route pursuit's chunk (B, steps, 2) [m/s, rad/s] from the view's route hint
        (``core.controllers.route_pursuit.pursuit_chunk``)."""
        _, dt, _ = safety_geometry()
        _, high = action_bounds()
        return pursuit_chunk(view.route, view.goal, steps, dt, high[1])

    def continuation(self, view: SafetyView) -> Callable[[np.ndarray], np.ndarray] | None:
        """What best-of-K assumes the team runs after a sequence: route pursuit for ``route_lookahead``
        steps from each end pose (B, P, 3) -> (B, P, n, 2); None without."""
        n = self.settings.route_lookahead
        if not n:
            return None
        _, dt, _ = safety_geometry()
        _, high = action_bounds()

        def continuation(end: np.ndarray) -> np.ndarray:
            B, P = end.shape[:2]
            route, goal = np.repeat(view.route, P, axis=0), np.repeat(view.goal, P, axis=0)
            out = pursuit_chunk(route, goal, n, dt, high[1], start=end.reshape(B * P, 3))
            return out.reshape(B, P, n, 2)

        return continuation

    def footprint_check(self, view: SafetyView) -> safety.FootprintCheck:
        """Best-of-K's check (``core.safety.filters.FootprintCheck``) on ``view``: the observed obstacles and
        velocities, the actuator start, route pursuit's lookahead."""
        return safety.FootprintCheck(
            view.obstacles,
            self.body,
            view.velocity,
            view.start,
            self.continuation(view),
            self.settings.mover_uncertainty,
        )

    def recheck(self, view: SafetyView, plans: np.ndarray) -> np.ndarray:
        """Whether the rest of each kept plan (B, T, 2) [m/s, rad/s] still passes best-of-K's check on
        this step's ``view`` (B,) bool (``core.safety.filters.plan_is_safe``); the failures are counted
        (``rechecks_failed``)."""
        safe = safety.plan_is_safe(plans, self.footprint_check(view), self.settings.margin)
        self.stats["rechecks_failed"] += int((~safe).sum())
        return safe

    def choose(
        self,
        seen,
        chunks: np.ndarray,
        last_action: np.ndarray | None = None,
        has_last=None,
        previous: np.ndarray | None = None,
        keep_to=None,
    ) -> tuple[np.ndarray, dict]:
        """Best-of-K (``core.safety.filters.select_chunk``): ``seen`` a ``SafetyView`` or a raw egocentric
        observation (B, D) (``observed_obstacles``), chunks (B, K, T, 2) [m/s, rad/s] -> kept chunks
        (B, T, 2), info (``select_chunk``'s, and ``proposal_kept`` (B,)). With ``blend_steps`` and the
        last executed actions (B, 2), the escape manoeuvres are blended into them as the sampled
        chunks were, and with ``proposal_blend`` route pursuit's proposal (where ``has_last``, default
        everywhere), then smoothed as the sampled chunks are (``chunk_smoothing``). ``previous``
        (B, n, 2): the plan being replaced, from now on, kept to where ``keep_to`` (B,) (default:
        everywhere) by the ``coherence`` preference; None: no such preference. Counts the replans
        where no sampled chunk was safe, the escapes, stops and proposals kept."""
        view = self._as_view(seen)
        body = self.body
        low, high = action_bounds()
        s = self.settings
        blend = None
        if last_action is not None and self.blend_steps:
            blend = (np.asarray(last_action), np.asarray(has_last), self.blend_steps)
        K = chunks.shape[1]
        if s.route_proposal:  # route pursuit's chunk competes with the sampled ones
            proposal = self.route_proposal(view, chunks.shape[2])
            if s.proposal_blend and last_action is not None and not self.knows_rate_limits:
                # enter from the running command (a rate-limited actuator ramps the step by itself)
                had = np.ones(len(proposal), bool) if has_last is None else np.asarray(has_last)
                last = np.asarray(last_action)
                proposal = blend_replan(proposal, last, had, s.proposal_blend)
                proposal = smooth_chunks(proposal, last, had, s.chunk_smoothing)
            chunks = np.concatenate([chunks, proposal[:, None]], axis=1)
        coherence = None
        if previous is not None and s.coherence:
            coherence = safety.PlanCoherence(
                np.asarray(previous),
                np.ones(len(chunks), bool) if keep_to is None else np.asarray(keep_to),
                np.asarray(high) - np.asarray(low),
                s.coherence,
            )
        chosen, info = safety.select_chunk(
            chunks,
            view.obstacles,
            view.goal,
            body.template,
            body.dt,
            body.agent_radius,
            s.margin,
            escape_advantage=self.escape_advantage,
            blend=blend,
            blocked_fallback=self.blocked_fallback,
            obstacle_velocity=view.velocity,
            start=view.start,
            continuation=self.continuation(view),
            coherence=coherence,
            progress_resolution=PROGRESS_RESOLUTION,
            progress_bilinear=True,
            primitives=_escape_lattice(ESCAPE_SPEEDS),
            mover_uncertainty=s.mover_uncertainty,
            halt_lookahead=s.halt_lookahead if s.moving_obstacles else 0,
            fallback_all=True,
        )
        info["proposal_kept"] = info["choice"] == K if s.route_proposal else np.zeros(len(chosen), bool)
        self.stats["replans_none_safe"] += int((~info["any_safe"]).sum())
        self.stats["escapes"] += int(info["escaped"].sum())
        self.stats["stops"] += int(info["stopped"].sum())
        self.stats["proposals"] += int(info["proposal_kept"].sum())
        return chosen, info

    # -- the filter, the actuator model and the guidance ---------------------------------------------
    def filter(self, seen, action: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The filter on [v, omega] (B, 2) -> (filtered, changed (B,)); ``seen`` as in ``choose``.
        "cbf": ``core.safety.filters.cbf_filter``; "none": the actions unchanged. Counts the changes
        (``filter_interventions``)."""
        action = np.asarray(action, dtype=np.float64)
        s = self.settings
        if s.filter != "cbf":
            return action, np.zeros(len(action), bool)
        view = self._as_view(seen)
        body = self.body
        low, high = action_bounds()
        out, changed = safety.cbf_filter(
            action,
            view.obstacles,
            body.template,
            body.agent_radius,
            s.margin,
            s.cbf_rate,
            np.asarray(low),
            np.asarray(high),
            obstacle_velocity=view.velocity,
            start=view.start,
            dt=body.dt,
        )
        self.stats["filter_interventions"] += int(changed.sum())
        return out, changed

    def send(self, rows: np.ndarray, commands: np.ndarray) -> None:
        """Record the commands (len(rows), 2) [m/s, rad/s] sent to episodes ``rows``, clipped to the
        action bounds: the actuator model runs the oldest in flight (or this one, without a delay) and
        queues this one."""
        s = self.settings
        low, high = action_bounds()
        sent = np.clip(np.asarray(commands, dtype=np.float64), low, high)
        runs = sent
        if s.action_delay:
            runs = self.in_flight[rows, 0]
            self.in_flight[rows, :-1] = self.in_flight[rows, 1:]
            self.in_flight[rows, -1] = sent
        _, dt, _ = safety_geometry()
        self.executed_velocity[rows] = rate_limit(
            self.executed_velocity[rows], runs, s.max_linear_accel, s.max_angular_accel, dt
        )

    def clearance_step(self, view: SafetyView) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        """One application of the clearance guidance (``guidance``) to commands of the B = len(view)
        episodes: (commands (n, T, 2) [m/s, rad/s] from the current step on, the episode of each row
        (n,)) -> the commands moved by one step of -eta dJ/da (``core.safety.guidance.clearance_cost_gradient``
        with ``GUIDANCE_DISTANCE``, on the view's obstacles from the actuator's predicted start), each
        clipped to the action bounds."""
        pose, steps = safety.chunk_origin(view.start, len(view.goal))
        velocity = view.velocity  # None unless the layer predicts moving obstacles
        low, high = (np.asarray(b) for b in action_bounds())
        eta = self.settings.guidance

        def step(moved: np.ndarray, at: np.ndarray) -> np.ndarray:
            _, grad = guidance.clearance_cost_gradient(
                pose[at],
                moved[:, None],
                view.obstacles[at],
                self.body,
                GUIDANCE_DISTANCE,
                None if velocity is None else velocity[at],
                steps,
            )
            return np.clip(moved - eta * grad[:, 0], low, high)

        return step
