"""The safety layer as one unit: its settings (``SafetySettings``, with what it is told of the world,
``KnownWorld``), what it sees of an episode at a step (``SafetyView``) and the layer itself
(``SafetyLayer``), NumPy only.

The layer sits between a planner's proposals and the robot. It takes numpy arrays in physical units
([v, omega] in m/s and rad/s, the body frame of ``core.safety.filters``) and owns, per episode of a batch,
what it must remember between steps: the commands in flight and the velocity the actuator model
executed last, the obstacle tracker (velocities) and the obstacle filter (sensing noise). Its calls:

- ``view(env_state, rows)``: what the layer sees of episodes ``rows`` at this step, from their raw
  egocentric observation (``observed_obstacles`` decodes it): the goal and obstacles of its
  ``nearest`` part; where its world (``KnownWorld``) has ``moving_obstacles`` their velocities (the
  encoding's, else the episode's ``core.perception.obstacle_tracker.ObstacleTracker`` estimates);
  with a known actuator (``action_delay``, ``max_linear_accel`` / ``max_angular_accel``) the
  ``core.safety.filters.ChunkStart`` after the commands in flight; with a known sensing noise
  (``obstacle_noise``, ``pose_noise``) the obstacles smoothed over the steps
  (``core.perception.obstacle_filter``). Call it once per step.
- ``choose(view, chunks)``: best-of-K (``core.safety.filters.select_chunk``) among candidate chunks
  (B, K, T, 2): with a route encoding route pursuit's chunk joins them (``ROUTE_PROPOSAL``) and
  every candidate is followed by route pursuit for ``horizon`` steps in the check (where none
  passes so and obstacles move, by braking for ``horizon`` steps), and the layer prefers the safe
  candidate closest to the plan it replaces (``COHERENCE``); escape manoeuvres of ``ESCAPE_SPEEDS``
  where nothing is safe, else the widest of every candidate scored; progress on a
  ``PROGRESS_RESOLUTION`` grid read bilinearly.
- ``recheck(view, plans)``: whether the rest of each kept plan still passes best-of-K's check on
  this step's view (``core.safety.filters.plan_is_safe``).
- ``filter(view, action)``: the filter on every executed action (``filter`` "cbf":
  ``core.safety.filters.cbf_filter``).
- ``send(rows, commands)``: the commands sent to episodes ``rows``, for the actuator model.
- ``clearance_step(view, eta)``: one step of the sampler's clearance guidance (step ``eta``, the
  replanner's ``guidance``; ``core.safety.guidance``) on the view's obstacles.

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
from dataclasses import dataclass, field, fields, replace

import numpy as np

from lerobot_formation.core.controllers.footprint import TeamBody
from lerobot_formation.core.controllers.route_pursuit import pursuit_chunk
from lerobot_formation.core.encodings.obstacle_grid import get_encoding
from lerobot_formation.core.perception.obstacle_filter import ObstacleFilter
from lerobot_formation.core.perception.obstacle_tracker import ObstacleTracker
from lerobot_formation.core.safety import filters as safety
from lerobot_formation.core.safety import guidance
from lerobot_formation.core.safety.filters import PROGRESS_RESOLUTION
from lerobot_formation.core.safety.lattice_search import search_proposals
from lerobot_formation.core.safety.replan_blend import blend_replan, smooth_chunks
from lerobot_formation.core.world.dynamics import FormationParams, rate_limit

# The shipped layer's settings that are no settings field:
ESCAPE_SPEEDS = (0.0, 0.1, 0.2, 0.3, 0.45, 0.6)  # [m/s] best-of-K's escape manoeuvres, each turn rate
GUIDANCE_DISTANCE = 0.3  # [m] the clearance below which the sampling guidance's cost grows
CBF_RATE = 4.0  # [1/s] the filter's barrier decay rate alpha: dh/dt >= -alpha h
FOLLOWER_MARGIN = 0.03  # [m] the followers' clearance on top of the margin (not where obstacles move)
ROUTE_PROPOSAL = True  # [bool] route pursuit's chunk joins best-of-K's candidates (with a route hint)
PROPOSAL_BLEND = 4  # [steps] route pursuit's proposal enters from the command being executed
COHERENCE = 1.0  # [m] best-of-K's weight on keeping to the plan it replaces (progress per unit of deviation)
FILTERS = ("none", "cbf")  # the per-action filters (``SafetySettings.filter``)

# What ``SafetyLayer.stats`` counts (module docstring).
LAYER_STAT_KEYS = (
    "replans_none_safe",
    "escapes",
    "stops",
    "filter_interventions",
    "proposals",
    "rechecks_failed",
    "searched",
)


def _finite_at_least(value, low: float) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, float)) and low <= value < math.inf


def _count(value) -> bool:
    """An integer >= 0 (a bool is not one)."""
    return not isinstance(value, bool) and isinstance(value, int) and value >= 0


class WorldError(ValueError):
    """A ``KnownWorld`` value refused; the message names the field and the value. A config error
    (``config_error``): a formation run's command line prints it as one line
    (``compat.run_checks.config_error_in_chain``)."""

    config_error = True


@dataclass(frozen=True)
class KnownWorld:
    """What the safety layer is told of the robot it runs on and of its world: properties a robot's
    designer knows, not tuned settings (the policy config's ``safety_world``; the bench tells it each
    level's conditions, ``known_world``). The defaults: nothing known (an exact, instant robot among
    standing obstacles); then the layer acts bit for bit as without it.

    Attributes:
        moving_obstacles: the layer predicts every observed obstacle at constant velocity (best-of-K
            checks a chunk against where the obstacles will be, the filter's barrier counts their
            approach): the velocities an encoding that observes them gives ("nearest+velocity"),
            else those of the layer's tracker (``core.perception.obstacle_tracker``).
        action_delay: [control steps] between sending a command and its execution (the env's
            ``action_delay``): best-of-K and the filter start from the pose predicted after the
            commands already sent.
        max_linear_accel: [m/s^2] the actuator's limit on dv/dt (the env's ``max_linear_accel``):
            best-of-K rolls chunks out rate limited (``dynamics.rate_limit``) and the filter chooses
            among the velocities one step can reach. None: no limit.
        max_angular_accel: [rad/s^2] the same on domega/dt (the env's ``max_angular_accel``).
        obstacle_noise: [m] the std of the noise on the observed obstacles' centres and radii (the
            env's ``obstacle_noise``). With either noise > 0 the layer smooths the obstacles it sees
            over the steps (``core.perception.obstacle_filter``): a barrier on raw noisy clearances
            lets a team that cannot back up creep into the obstacle it waits beside.
        pose_noise: [m, rad] the same for the observed midpoint pose (the env's ``pose_noise``).
    """

    moving_obstacles: bool = False
    action_delay: int = 0
    max_linear_accel: float | None = None
    max_angular_accel: float | None = None
    obstacle_noise: float = 0.0
    pose_noise: float = 0.0

    def __post_init__(self):
        def refuse(name: str, want: str) -> None:
            raise WorldError(f"safety_world.{name} must be {want}, got {getattr(self, name)!r}")

        if not isinstance(self.moving_obstacles, bool):
            refuse("moving_obstacles", "true or false")
        if not _count(self.action_delay):
            refuse("action_delay", "an integer >= 0 [control steps]")
        for name in ("max_linear_accel", "max_angular_accel"):
            value = getattr(self, name)
            if value is not None and not (_finite_at_least(value, 0.0) and value > 0):
                refuse(name, "null (no limit) or a finite number > 0")
        for name in ("obstacle_noise", "pose_noise"):
            if not _finite_at_least(getattr(self, name), 0.0):
                refuse(name, "a finite std >= 0")


def _config(name: str):
    """A settings field's metadata: the policy config field it is read from (``from_config``)."""
    return {"config": name}


@dataclass(frozen=True)
class SafetySettings:
    """What the safety layer is set to, in one value. The defaults are the shipped default's (a
    ``FormationDiffusionConfig()``'s); each field is read from one policy config field
    (``from_config``; the name in brackets), whose docstring describes it. The layer's other settings
    are wired (the module's constants); the sampler's (chunk smoothing, the guidance step) are the
    replanner's, and the observation's layout is the layer's constructor's.

    Attributes:
        filter: the filter on every executed action, "none" or "cbf" (``safety_filter``).
        margin: [m] the clearance kept between every agent disc and every obstacle (``safety_margin``).
        horizon: [steps] the layer looks past every candidate chunk: route pursuit after it (with a
            route hint); where no candidate passes so and obstacles move, braking after it
            (``safety_horizon``).
        mover_uncertainty: [m/s] the growth of a moving obstacle's predicted radius per second ahead
            (``safety_mover_uncertainty``).
        world: what the layer is told of the robot and its world (``safety_world``, ``KnownWorld``).
        search: where the layer predicts moving obstacles, the lattice search's paths that join the
            candidates, the best of each of its ``search`` best first manoeuvres
            (``core.safety.lattice_search``); 0: no search (``safety_search``).
    """

    filter: str = field(default="cbf", metadata=_config("safety_filter"))
    margin: float = field(default=0.05, metadata=_config("safety_margin"))
    horizon: int = field(default=20, metadata=_config("safety_horizon"))
    mover_uncertainty: float = field(default=0.1, metadata=_config("safety_mover_uncertainty"))
    world: KnownWorld = field(default_factory=KnownWorld, metadata=_config("safety_world"))
    search: int = field(default=3, metadata=_config("safety_search"))

    def __post_init__(self):
        def refuse(name: str, want: str) -> None:
            value = getattr(self, name)
            raise ValueError(f"{name} ({CONFIG_FIELDS[name]}) must be {want}, got {value!r}")

        if self.filter not in FILTERS:
            refuse("filter", f"one of {FILTERS}")
        for name in ("margin", "mover_uncertainty"):
            if not _finite_at_least(getattr(self, name), 0.0):
                refuse(name, "a finite number >= 0")
        if not _count(self.horizon):
            refuse("horizon", "an integer >= 0")
        if not _count(self.search):
            refuse("search", "an integer >= 0")
        if not isinstance(self.world, KnownWorld):
            refuse("world", "a KnownWorld")

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


# settings field -> the policy config field it is read from (``SafetySettings.from_config``)
CONFIG_FIELDS: dict[str, str] = {f.name: f.metadata["config"] for f in fields(SafetySettings)}


def known_world(conditions, scenes_move: bool = False) -> KnownWorld | None:
    """What the layer is told of a run under ``conditions`` (``core.perception.conditions.Conditions``
    or None): the actuator's delay and acceleration limits, the sensors' noise stds, and whether
    obstacles move: ``moving_obstacles`` of the conditions, or ``scenes_move`` (the scenes give their
    obstacles' velocities). What a robot's designer knows of the world, never its noise draws. None
    when neither conditions nor moving scenes (nothing to tell)."""
    world = None
    if conditions is not None and conditions.enabled:
        world = KnownWorld(
            moving_obstacles=conditions.moving_obstacles > 0,
            action_delay=conditions.action_delay,
            max_linear_accel=conditions.max_linear_accel,
            max_angular_accel=conditions.max_angular_accel,
            obstacle_noise=conditions.obstacle_noise,
            pose_noise=conditions.pose_noise,
        )
    if scenes_move:
        world = replace(world or KnownWorld(), moving_obstacles=True)
    return world


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
        settings: what it is set to (default: the shipped default's, ``SafetySettings()``).
        encoding: the observation's obstacle encoding it decodes (the policy config's
            ``obstacle_encoding``; default the shipped policy's, "nearest+route").
        max_obstacles: its obstacle slots, None: the encoding's default (``max_obstacles``).
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
        encoding: str = "nearest+route",
        max_obstacles: int | None = None,
        blend_steps: int = 0,
        escape_advantage: float | None = None,
        blocked_fallback: str = "widest",
    ):
        self.settings = SafetySettings() if settings is None else settings
        self.blend_steps = blend_steps
        self.escape_advantage = escape_advantage
        self.blocked_fallback = blocked_fallback
        self.encoding = get_encoding(encoding)
        self.slots = self.encoding.slots(max_obstacles)
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
        w = self.settings.world
        _, dt, _ = safety_geometry()
        self.in_flight = np.zeros((B, w.action_delay, 2))  # sent, not run yet; oldest first
        self.executed_velocity = np.zeros((B, 2))  # the actuator model's last executed [v, omega]
        self.tracker = self.smoother = None
        if w.moving_obstacles and not self.encoding.velocity:
            self.tracker = ObstacleTracker(B, self.slots, dt)
        if self.knows_noise:
            self.smoother = ObstacleFilter(
                B, self.slots, dt, obstacle_noise=w.obstacle_noise, pose_noise=w.pose_noise
            )

    @property
    def knows_actuator(self) -> bool:
        """Whether the layer knows the actuator's delay or rate limits (``SafetyView.start``)."""
        return bool(self.settings.world.action_delay or self.knows_rate_limits)

    @property
    def knows_rate_limits(self) -> bool:
        """Whether the layer knows the actuator's rate limits (it then ramps a step in [v, omega])."""
        w = self.settings.world
        return w.max_linear_accel is not None or w.max_angular_accel is not None

    @property
    def knows_noise(self) -> bool:
        """Whether the layer knows the sensors' noise (then the view is smoothed)."""
        return self.settings.world.obstacle_noise > 0 or self.settings.world.pose_noise > 0

    @property
    def tracks_commands(self) -> bool:
        """Whether the layer needs the commands sent (``send``): for the actuator model or the
        smoothing's motion."""
        return self.knows_actuator or self.knows_noise

    @property
    def agent_radii(self) -> float | np.ndarray:
        """The agent radius the layer checks: one per template agent (N,), the followers' (agents 2
        and 3) larger by ``FOLLOWER_MARGIN`` (they lag their slots, most in turns and under noise);
        one for all four where the layer predicts moving obstacles (the world's ``moving_obstacles``),
        where the team needs its room to get out of a mover's way (on level5's tuning scenes 0.03 m
        cost 21 of 200)."""
        template, _, agent_radius = safety_geometry()
        extra = FOLLOWER_MARGIN
        if not extra or self.settings.world.moving_obstacles:
            return agent_radius
        return agent_radius + extra * (np.arange(len(template)) >= 2)  # the first two are the leaders

    # -- what the layer sees -------------------------------------------------------------------------
    def observed_obstacles(self, env_state: np.ndarray) -> SafetyView:
        """Goal (B, 2), obstacles (B, M, 3) and mask (B, M) in the body frame from a raw egocentric
        observation (B, D), and with the world's ``moving_obstacles`` the velocities an encoding that observes
        them gives (``nearest+velocity``: after the rows), and a route encoding's carrots; no
        tracker, no actuator."""
        encoding, slots = self.encoding, self.slots
        env = np.asarray(env_state)
        rows_end = encoding.fixed + encoding.per_slot * slots
        # the nearest part only (e.g. "nearest+route" adds a route hint, "nearest+velocity" velocities)
        goal, obstacles, mask = safety.decode_nearest(env[:, :rows_end], slots)
        velocity = None
        if self.settings.world.moving_obstacles and encoding.velocity:
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
        w = self.settings.world
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
                self.in_flight[idx], self.executed_velocity[idx], dt, w.max_linear_accel, w.max_angular_accel
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
        """What best-of-K assumes the team runs after a sequence: route pursuit for ``horizon`` steps
        from each end pose (B, P, 3) -> (B, P, n, 2); None without a horizon or a route hint."""
        n = self.settings.horizon if self.encoding.map else 0
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
        *,
        chunk_smoothing: int = 0,
    ) -> tuple[np.ndarray, dict]:
        """Best-of-K (``core.safety.filters.select_chunk``): ``seen`` a ``SafetyView`` or a raw egocentric
        observation (B, D) (``observed_obstacles``), chunks (B, K, T, 2) [m/s, rad/s] -> kept chunks
        (B, T, 2), info (``select_chunk``'s, and ``proposal_kept`` (B,)). With ``blend_steps`` and the
        last executed actions (B, 2), the escape manoeuvres are blended into them as the sampled
        chunks were, and route pursuit's proposal (with a route hint, ``ROUTE_PROPOSAL``) over its
        first ``PROPOSAL_BLEND`` steps (where ``has_last``, default everywhere; not with a
        rate-limited actuator, which ramps that step by itself), then smoothed as the sampler's
        chunks are (``chunk_smoothing`` passes, the replanner's). ``previous`` (B, n, 2): the plan
        being replaced, from now on, kept to where ``keep_to`` (B,) (default: everywhere) by the
        ``COHERENCE`` preference; None: no such preference. Counts the replans where no sampled
        chunk was safe, the escapes, stops and proposals kept."""
        view = self._as_view(seen)
        body = self.body
        low, high = action_bounds()
        s = self.settings
        blend = None
        if last_action is not None and self.blend_steps:
            blend = (np.asarray(last_action), np.asarray(has_last), self.blend_steps)
        K = chunks.shape[1]
        proposes = ROUTE_PROPOSAL and bool(self.encoding.map)
        if proposes:  # route pursuit's chunk competes with the sampled ones
            proposal = self.route_proposal(view, chunks.shape[2])
            if PROPOSAL_BLEND and last_action is not None and not self.knows_rate_limits:
                # enter from the running command (a rate-limited actuator ramps the step by itself)
                had = np.ones(len(proposal), bool) if has_last is None else np.asarray(has_last)
                last = np.asarray(last_action)
                proposal = blend_replan(proposal, last, had, PROPOSAL_BLEND)
                proposal = smooth_chunks(proposal, last, had, chunk_smoothing)
            chunks = np.concatenate([chunks, proposal[:, None]], axis=1)
        searched_from = chunks.shape[1]
        if s.search and s.world.moving_obstacles:  # the lattice search's ways past the movers compete too
            found = search_proposals(
                self.footprint_check(view), view.goal, s.margin, chunks.shape[2], s.search
            )
            chunks = np.concatenate([chunks, found], axis=1)
        coherence = None
        if previous is not None and COHERENCE:
            coherence = safety.PlanCoherence(
                np.asarray(previous),
                np.ones(len(chunks), bool) if keep_to is None else np.asarray(keep_to),
                np.asarray(high) - np.asarray(low),
                COHERENCE,
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
            halt_lookahead=s.horizon if s.world.moving_obstacles else 0,
            fallback_all=True,
        )
        info["proposal_kept"] = info["choice"] == K if proposes else np.zeros(len(chosen), bool)
        info["search_kept"] = (info["choice"] >= searched_from) & (info["choice"] < chunks.shape[1])
        self.stats["searched"] += int(info["search_kept"].sum())
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
            CBF_RATE,
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
        w = self.settings.world
        low, high = action_bounds()
        sent = np.clip(np.asarray(commands, dtype=np.float64), low, high)
        runs = sent
        if w.action_delay:
            runs = self.in_flight[rows, 0]
            self.in_flight[rows, :-1] = self.in_flight[rows, 1:]
            self.in_flight[rows, -1] = sent
        _, dt, _ = safety_geometry()
        self.executed_velocity[rows] = rate_limit(
            self.executed_velocity[rows], runs, w.max_linear_accel, w.max_angular_accel, dt
        )

    def clearance_step(self, view: SafetyView, eta: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        """One application of the clearance guidance of step ``eta`` (the sampler's guidance, the
        replanner's ``guidance``) to commands of the B = len(view) episodes: (commands (n, T, 2)
        [m/s, rad/s] from the current step on, the episode of each row (n,)) -> the commands moved
        by one step of -eta dJ/da (``core.safety.guidance.clearance_cost_gradient``
        with ``GUIDANCE_DISTANCE``, on the view's obstacles from the actuator's predicted start), each
        clipped to the action bounds."""
        pose, steps = safety.chunk_origin(view.start, len(view.goal))
        velocity = view.velocity  # None unless the layer predicts moving obstacles
        low, high = (np.asarray(b) for b in action_bounds())

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
