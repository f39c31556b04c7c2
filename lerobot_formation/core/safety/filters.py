"""The learned planner's safety layer: best-of-K chunk selection and a control-barrier-function filter.

Everything here works in the midpoint's body frame (x right, y along the heading; the midpoint at the
origin, pose ``BODY_POSE``), which is what the egocentric ``nearest`` encoding observes, so the layer
needs nothing but the policy's own observation: no privileged state. The followers are assumed to sit
on their square slots (the formation template); they track them within ~0.1 m, which ``margin``
covers, or, where ``agent_radius`` is given per template agent, the followers' larger radius (their
allowance for the lag) with it.

``select_chunk`` (best-of-K, the "safest" rule of adaptive sampling):
  1. roll each candidate chunk's whole horizon through the midpoint unicycle and place the rigid
     formation footprint (all four agents) at every step (``footprint.sequence_clearance``);
  2. discard candidates that come within ``margin`` of an obstacle (when the team is already inside
     the margin, those that come closer than it is now, minus 2 cm);
  3. among the rest keep the one with the most progress toward the goal: the decrease of a grid
     cost-to-go around the observed obstacles (``cost_to_go_progress``; straight-line progress is
     greedy and drives into obstacles, clearance alone would steer away from the goal too);
  (with a ``continuation``, e.g. route pursuit after the chunk: steps 2-3 also cover it, so that a
  chunk leaving the team nose-in at a wall it cannot turn away from loses, and progress counts the
  heading it leaves; a preference, dropped where no candidate's continuation is safe; there, with a
  ``halt_lookahead``, the candidates after which the team can brake and stand clear of the movers
  are preferred: ``FootprintCheck.halted``)
  4. if none is safe, a safe escape manoeuvre (a turn in place or an arc, ``escape_primitives``)
     with the most progress; if none of those is safe either (``blocked_fallback``): "widest", the
     sampled candidate with the largest predicted clearance (with ``fallback_all``, of the sampled
     chunks and manoeuvres; a CBF filter then brakes); "stop", the
     chunk or manoeuvre with the largest predicted clearance if it predicts no contact, else a stop
     (zero actions for the chunk, not blended: the leaders are kinematic, and a stopped team stays
     clear) and a fresh draw at the next replan.

``cbf_filter`` (the per-step filter): with agent i at body offset b_i, obstacle j at c_j with radius
r_j and h_ij = |p_i - c_j| - r_j - agent_radius - margin, the unicycle moves agent i at
p_i' = v e_y + omega (-b_iy, b_ix) (the team rotates about the midpoint). With n_ij the unit vector
from c_j to p_i, the barrier condition dh_ij/dt >= -alpha h_ij is linear in u = [v, omega]:

    n_ij . e_y v + n_ij . (-b_iy, b_ix) omega >= -alpha h_ij.

The filter solves min (u - u_nom)^T W (u - u_nom) subject to these rows and the action box, W the
inverse squared action ranges. The QP is two-dimensional, so it is solved exactly: its optimum is
u_nom, a projection onto one constraint line, or a vertex of two; all are enumerated (batched) and
the feasible one of least cost is kept. u = (0, 0) satisfies every row when the team is currently
safe (h >= 0), so the QP is then always feasible: stopping is the fallback. If the team is already
inside the margin, the candidate of least violation is taken.

Moving obstacles (``obstacle_velocity``, body-frame velocities v_j of the observed obstacles, from
the ``nearest+velocity`` encoding or ``core.perception.obstacle_tracker``): ``select_chunk`` checks the pose
after each action against the obstacles where they will be then, c_j + v_j t (constant velocity);
the filter's barrier h_ij = |p_i - c_j(t)| - r_j - ... has dh_ij/dt = n_ij . (p_i' - v_j), so its
row becomes n_ij . e_y v + n_ij . (-b_iy, b_ix) omega >= -alpha h_ij + n_ij . v_j (an approaching
obstacle asks for more than a standing one). With a ``mover_uncertainty`` u, best-of-K grows a moving
obstacle's radius by u t at t seconds ahead: its constant-velocity prediction is least sure at the end
of the horizon (velocity error, bounces). The leaders cannot back up, so a mover that comes up behind
the team is escaped only by outrunning it: the manoeuvres' speeds (``escape_primitives``) may go up to
the action bound.

Delay and rate limits (``ChunkStart``, from ``predict_start``): the commands already sent run first
(``delay`` steps), so a new chunk (and the filtered action) starts at the pose predicted after them,
with the obstacles moved on by as many steps; with acceleration limits every command sequence is
rolled out as the actuator executes it (``dynamics.rate_limit_sequence`` from the velocity executed
last), and the filter's action box shrinks to the velocities reachable in one step from it
(an action that only the rate limit changes is not an intervention).

Sensing noise: with noisy observations a barrier on the observed clearance h_obs = h + e is not one
on h. The leaders cannot back up (v >= 0), so each step the filter lets the team in by alpha dt h_obs
when a draw says there is room, and only stops it when a draw says there is none: dwelling beside an
obstacle, the team ratchets in until h is about the largest draw of -e, several stds below zero after
hundreds of steps (under level4 15 of 100 tuning episodes ended in 0.4-16 mm grazes at a standstill
with a 5 cm margin). So where the sensing noise is known the replanner smooths the obstacles the layer
sees (``core.perception.obstacle_filter``, a Kalman gain per obstacle): the std of e falls, to 0.1 of the raw
for a team that stands, and ``margin`` should be about three times what is left (a measurement-robust barrier: Dean et al. 2020, "Guaranteeing Safety of
Learned Perception Modules via Measurement-Robust Control Barrier Functions").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from lerobot_formation.core.controllers.footprint import TeamBody, sequence_clearance
from lerobot_formation.core.encodings.encoding import BODY_POSE, world_to_body
from lerobot_formation.core.encodings.velocity_encoding import body_velocities
from lerobot_formation.core.safety.replan_blend import blend_replan
from lerobot_formation.core.world.dynamics import rate_limit_sequence, rollout_poses
from lerobot_formation.core.world.navigation import cost_to_go_at
from lerobot_formation.core.world.scenes import FAR


@dataclass(frozen=True)
class ChunkStart:
    """Where the next command starts to act, in the current body frame (module docstring).

    Attributes:
        pose: (B, 3) the midpoint pose predicted after the commands in flight.
        velocity: (B, 2) the [v, omega] executed over the step before the next command runs.
        steps: the steps from now until the next command runs (the actuator's delay).
        max_linear_accel: the actuator's limit on dv/dt [m/s^2] (None: none).
        max_angular_accel: the same on domega/dt [rad/s^2] (None: none).
    """

    pose: np.ndarray
    velocity: np.ndarray
    steps: int = 0
    max_linear_accel: float | None = None
    max_angular_accel: float | None = None

    def __getitem__(self, rows) -> ChunkStart:
        return ChunkStart(
            self.pose[rows], self.velocity[rows], self.steps, self.max_linear_accel, self.max_angular_accel
        )

    def executed(self, commands: np.ndarray, dt: float) -> np.ndarray:
        """The velocities (B, C, T, 2) the actuator executes for command sequences (B, C, T, 2)."""
        return rate_limit_sequence(self.velocity, commands, self.max_linear_accel, self.max_angular_accel, dt)


@dataclass(frozen=True)
class PlanCoherence:
    """Best-of-K's preference for the plan it replaces (backward coherence, as in bidirectional
    decoding: Liu et al. 2024, "Bidirectional Decoding: Improving Action Chunking via Closed-Loop
    Resampling"). K samples of one observation differ; keeping the one with the most progress at
    every replan switches between them, which is what makes best-of-K jerkier than one sample.

    Attributes:
        previous: (B, n, 2) [v, omega] the plan being replaced, from the current step on.
        keep_to: (B,) where to keep to it (e.g. not where the filter cut it short: it met a barrier).
        ranges: (2,) the action ranges, the unit of the deviation.
        weight: w [m of progress] per unit of deviation.
    """

    previous: np.ndarray
    keep_to: np.ndarray
    ranges: np.ndarray
    weight: float

    def penalty(self, pool: np.ndarray) -> np.ndarray:
        """(B, P) w d for candidates (B, P, T, 2): d the root mean square deviation of their first n
        commands from ``previous``, in action ranges; 0 where not ``keep_to``."""
        n = self.previous.shape[1]
        gap = (pool[:, :, :n] - self.previous[:, None]) / np.asarray(self.ranges)
        deviation = np.sqrt((gap**2).sum(-1).mean(-1))
        return self.weight * np.where(np.asarray(self.keep_to)[:, None], deviation, 0.0)


def predict_start(
    in_flight: np.ndarray,
    executed: np.ndarray,
    dt: float,
    max_linear_accel: float | None = None,
    max_angular_accel: float | None = None,
) -> ChunkStart:
    """The ``ChunkStart`` after the commands in flight (B, d, 2) [v, omega] (oldest first: sent but
    not run yet, d = the delay), from the velocity executed last (B, 2): they run as the actuator runs
    them (rate limited), from ``BODY_POSE``."""
    B, d = in_flight.shape[:2]
    pose = np.broadcast_to(BODY_POSE, (B, 3)).copy()
    velocity = np.asarray(executed, dtype=np.float64)
    if d:
        run = rate_limit_sequence(velocity, in_flight[:, None], max_linear_accel, max_angular_accel, dt)
        pose = rollout_poses(pose, run, dt)[:, 0, -1]
        velocity = np.array(run[:, 0, -1], dtype=np.float64)
    return ChunkStart(pose, velocity, d, max_linear_accel, max_angular_accel)


def chunk_origin(start: ChunkStart | None, B: int) -> tuple[np.ndarray, int]:
    """Where B command sequences start (B, 3) in the body frame, and the steps until the first runs:
    the ``start``'s predicted pose and delay, or without one ``BODY_POSE`` at once."""
    if start is None:
        return np.broadcast_to(BODY_POSE, (B, 3)), 0
    return start.pose, start.steps


def obstacles_at_start(
    obstacles: np.ndarray, obstacle_velocity: np.ndarray | None, start: ChunkStart | None, dt: float
) -> tuple[np.ndarray, np.ndarray | None]:
    """Obstacles (B, M, 3) and their velocities (B, M, 2) in the body frame of the ``start`` pose,
    moved on by its ``steps`` (the filter's view when the next action runs); unchanged without a start."""
    if start is None:
        return obstacles, obstacle_velocity
    obstacles = np.array(obstacles, dtype=np.float64)
    if obstacle_velocity is not None:
        obstacles[..., :2] += obstacle_velocity * (start.steps * dt)
    obstacles[..., :2] = world_to_body(obstacles[..., :2], start.pose)
    if obstacle_velocity is not None:  # a direction: the rotation alone
        obstacle_velocity = body_velocities(obstacle_velocity, start.pose)
    return obstacles, obstacle_velocity


def decode_nearest(env_state: np.ndarray, slots: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``nearest`` encoding (B, 2 + 4 slots) -> goal (B, 2), obstacles (B, slots, 3), mask (B, slots)
    in the body frame; empty slots far away with radius 0."""
    env_state = np.asarray(env_state, dtype=np.float64)
    if env_state.ndim != 2 or env_state.shape[1] != 2 + 4 * slots:
        raise ValueError(
            f"the 'nearest' encoding with {slots} slots has {2 + 4 * slots} values, got shape {env_state.shape}"
        )
    goal = env_state[:, :2]
    rows = env_state[:, 2:].reshape(len(env_state), slots, 4)
    mask = rows[..., 3] > 0.5
    obstacles = np.where(mask[..., None], rows[..., :3], np.array([FAR, FAR, 0.0]))
    return goal, obstacles, mask


# Escape manoeuvres [v, omega], held over a chunk: a lattice of turns in place and arcs. Used only
# when no sampled chunk is safe, so that the team goes round a blocked heading (the safe arc with the
# most cost-to-go progress) instead of pressing against the obstacle while the filter holds it.
SLIDE_TOLERANCE = 0.02  # [m] how much closer than now a chunk may come when already inside the margin
BLOCKED_FALLBACKS = ("widest", "stop")
ESCAPE_SPEEDS = (0.0, 0.1, 0.2, 0.3)  # [m/s] the default lattice: turns in place and slow arcs
PROGRESS_WINDOW = 6.0  # [m] best-of-K's cost-to-go grid reaches +-(window + 2) m (``cost_to_go_progress``)
PROGRESS_INFLATE = 0.9  # [m] cells this near an obstacle cost ``PROGRESS_WALL_COST`` times more (as MPPI's)
PROGRESS_WALL_COST = 3.0
PROGRESS_RESOLUTION = 0.4  # [m] the cell of the grid the shipped layer reads (bilinearly) progress on
ESCAPE_TURN_RATES = (-1.5, -1.0, -0.5, -0.25, 0.0, 0.25, 0.5, 1.0, 1.5)  # [rad/s]


def escape_primitives(speeds=ESCAPE_SPEEDS) -> np.ndarray:
    """The escape manoeuvres (P, 2) [v, omega]: every speed of ``speeds`` [m/s] with every turn rate of
    ``ESCAPE_TURN_RATES``, less the standstill. Speeds above a mover's let the team outrun one that
    comes up behind it (a turn or a slow arc is struck)."""
    return np.array(
        [[v, w] for v in speeds for w in ESCAPE_TURN_RATES if (v, w) != (0.0, 0.0)], dtype=np.float64
    )


ESCAPE_PRIMITIVES = escape_primitives()


@dataclass(frozen=True)
class FootprintCheck:
    """Best-of-K's check of command sequences (steps 1-2 of the module docstring), one implementation
    for ``select_chunk`` and ``plan_is_safe``: the obstacles (B, M, 3) and their velocities (B, M, 2)
    (None: static) in the body frame, the team's ``body`` (``footprint.TeamBody``), ``start`` (``ChunkStart``; None: the
    commands run from now, as commanded), ``continuation`` (what the team runs after a sequence, from
    its end poses; ``select_chunk``) and ``mover_uncertainty`` (the growth of a mover's radius [m/s])."""

    obstacles: np.ndarray
    body: TeamBody
    obstacle_velocity: np.ndarray | None = None
    start: ChunkStart | None = None
    continuation: Callable[[np.ndarray], np.ndarray] | None = None
    mover_uncertainty: float = 0.0

    def _origin(self) -> tuple[np.ndarray, int]:
        return chunk_origin(self.start, len(self.obstacles))

    def floor(self, margin: float) -> np.ndarray:
        """(B, 1) the clearance a sequence must keep: ``margin``, or where the team is already inside
        it (the filter holds it at its edge), no closer than now less ``SLIDE_TOLERANCE``, so that it
        may slide along an obstacle instead of stalling there."""
        pose, steps = self._origin()
        now, _ = sequence_clearance(  # at the start (steps from now), standing
            pose,
            np.zeros((len(pose), 1, 1, 2)),
            self.obstacles,
            self.body,
            self.obstacle_velocity,
            steps - 1,
            self.mover_uncertainty,
        )
        return np.minimum(margin, now - SLIDE_TOLERANCE)

    def footprint(
        self, commands: np.ndarray, floor: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """Smallest clearance (B, C) over the sequences, over sequence and continuation (None without
        one), and the end poses (B, C, 3) progress is measured at, of commands (B, C, T, 2).

        With ``floor`` (B, 1), the continuation is rolled out only after the sequences that keep it
        (a sequence that does not cannot be safe with any continuation): for the others the second
        value is their own clearance and the end pose their own end. What is safe, and the progress
        of what is, are the same; the saving is most of the escape lattice's lookahead where nothing
        is safe."""
        pose, steps = self._origin()
        B, T = len(pose), commands.shape[2]
        run = commands if self.start is None else self.start.executed(commands, self.body.dt)
        obstacles, velocity, u = self.obstacles, self.obstacle_velocity, self.mover_uncertainty
        clear, end = sequence_clearance(pose, run, obstacles, self.body, velocity, steps, u)
        if self.continuation is None:
            return clear, None, end
        P = clear.shape[1]
        keep = np.ones((B, P), dtype=bool) if floor is None else clear >= floor
        W = int(keep.sum(axis=1).max())
        if W == 0:
            return clear, clear.copy(), end
        # the kept sequences first in each row (a permutation, so the padding writes back what it read)
        order = np.argsort(~keep, axis=1, kind="stable")[:, :W]
        picked = np.take_along_axis(keep, order, axis=1)
        at = np.take_along_axis(end, order[..., None], axis=1)  # (B, W, 3)
        more = self.continuation(at)  # the footprint after the sequence, too
        C = more.shape[2]
        after, after_end = sequence_clearance(
            at.reshape(B * W, 3),
            more.reshape(B * W, 1, C, 2),
            np.repeat(obstacles, W, axis=0),
            self.body,
            None if velocity is None else np.repeat(velocity, W, axis=0),
            steps + T,
            u,
        )
        own = np.take_along_axis(clear, order, axis=1)
        viable, last = clear.copy(), end.copy()
        np.put_along_axis(viable, order, np.where(picked, np.minimum(own, after.reshape(B, W)), own), axis=1)
        # progress counts the continuation: heading matters
        np.put_along_axis(
            last, order[..., None], np.where(picked[..., None], after_end.reshape(B, W, 3), at), axis=1
        )
        return clear, viable, last

    def _alone(self, rows: np.ndarray) -> FootprintCheck:
        """The same check of episodes ``rows``, of the sequences alone (no continuation)."""
        return replace(
            self,
            obstacles=self.obstacles[rows],
            obstacle_velocity=None if self.obstacle_velocity is None else self.obstacle_velocity[rows],
            start=None if self.start is None else self.start[rows],
            continuation=None,
        )

    def halted(self, commands: np.ndarray, steps: int, rows: np.ndarray | None = None) -> np.ndarray:
        """Smallest clearance (R, C) of command sequences (R, C, T, 2) of episodes ``rows`` (R,)
        (default: the first R), each followed by ``steps`` zero commands (braked as the actuator
        brakes, then standing): whether the team may stop where a sequence leaves it
        (``select_chunk``'s ``halt_lookahead``). Against standing obstacles it is the sequence's own
        clearance, or its braking distance's; a mover that walks into the standing team lowers it."""
        R, C = commands.shape[:2]
        rows = np.arange(R) if rows is None else rows
        stop = np.zeros((R, C, steps, 2))
        return self._alone(rows).footprint(np.concatenate([commands, stop], axis=2))[0]


def plan_is_safe(plan: np.ndarray, check: FootprintCheck, margin: float) -> np.ndarray:
    """Whether each plan (B, T, 2) [v, omega] (e.g. the rest of the chunk being executed) still passes
    best-of-K's check on a newer view (B,) bool: the plan and, with the check's continuation, what
    follows it keep ``check.floor(margin)``. Where it fails the replanner replans at once
    (best-of-K's recheck): a chunk kept as safe is otherwise run for n_action_steps on the view it was
    scored on, while a mover's estimated velocity and the sensed obstacles change under it."""
    floor = check.floor(margin)
    clear, viable, _ = check.footprint(np.asarray(plan, dtype=np.float64)[:, None], floor)
    return (clear if viable is None else viable)[:, 0] >= floor[:, 0]


def select_chunk(
    candidates: np.ndarray,
    obstacles: np.ndarray,
    goal: np.ndarray,
    template: np.ndarray,
    dt: float,
    agent_radius: float | np.ndarray,
    margin: float,
    escape_advantage: float | None = None,
    blend: tuple[np.ndarray, np.ndarray, int] | None = None,
    blocked_fallback: str = "widest",
    obstacle_velocity: np.ndarray | None = None,
    start: ChunkStart | None = None,
    continuation: Callable[[np.ndarray], np.ndarray] | None = None,
    coherence: PlanCoherence | None = None,
    progress_resolution: float = 0.2,
    progress_bilinear: bool = False,
    primitives: np.ndarray | None = None,
    mover_uncertainty: float = 0.0,
    fallback_all: bool = False,
    halt_lookahead: int = 0,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The kept chunk (B, T, 2) [v, omega] among candidates (B, K, T, 2), and diagnostics.

    ``obstacles`` (B, M, 3) and ``goal`` (B, 2) are in the body frame. Progress is the cost-to-go's
    (``cost_to_go_progress`` within ``PROGRESS_WINDOW`` m). When no candidate is safe the safe escape
    manoeuvre (``primitives``) with the most progress is kept, if any.
    With ``escape_advantage`` (metres), a safe primitive is also kept when its progress beats every
    safe sampled chunk's by that much: a team the policy keeps pressing against an obstacle (its
    chunks safe only because they barely move) goes round it instead of timing out there.
    ``info["choice"]`` is the kept index (K + j for primitive j). ``blend`` = (last executed action
    (B, 2), whether there is one (B,), m): the primitives are blended into the executed action as the
    caller blended the sampled chunks (``core.safety.replan_blend``), so what is scored is what will run.
    ``blocked_fallback`` (step 4 of the module docstring): "widest" or "stop"; ``info["blocked"]`` says
    where nothing scored was safe (the fallback kept; "escaped" then only says it is a manoeuvre),
    ``info["stopped"]`` where the team stops. ``obstacle_velocity`` (B, M, 2): the obstacles' velocities (None: static);
    ``start``: the commands in flight and the rate limits (``predict_start``; None: the chunk runs
    from now, as commanded). Either changes only the predicted clearances, never the kept chunk's
    commands. ``continuation``: a function of the candidates' end poses (B, K', 3) (body frame) that
    returns the commands (B, K', C, 2) the team would run after them (e.g. route pursuit's,
    ``core.controllers.route_pursuit.pursuit_chunk``); a candidate is then safe only if its continuation is too
    (one that ends nose-in at a wall it cannot turn away from, the leaders unable to back up, is
    not), unless no candidate's continuation is safe: then the chunks alone decide. Progress is then
    measured at the continuation's end, so a chunk that leaves the team facing its way scores the
    progress it makes possible (the leaders' heading matters: they cannot back up); the continuation
    is rolled out only after the candidates that keep the margin (``FootprintCheck.footprint``), so
    ``info["progress"]`` of one that does not is measured at its own end (it is never kept for it).
    ``coherence`` (``PlanCoherence``): among the safe candidates, one whose first n commands deviate
    from the plan being replaced by d (root mean square, in units of the action ranges) scores w d
    less progress; it ranks safe candidates only, never makes one safe.
    ``progress_resolution``: the cost-to-go grid's cell size [m]; ``progress_bilinear``: read it
    bilinearly, not at the nearest cell (``cost_to_go_progress``).
    ``primitives`` (P, 2): the escape manoeuvres (default ``ESCAPE_PRIMITIVES``, ``escape_primitives``).
    ``fallback_all``: the "widest" fallback keeps the widest of every candidate scored (sampled chunks
    and manoeuvres, e.g. a fast arc that a mover strikes later or less deep), not of the sampled
    chunks only.
    ``mover_uncertainty`` [m/s]: with ``obstacle_velocity``, a moving obstacle's predicted radius grows
    by that much per second ahead (``core.perception.obstacle_tracker.predict_obstacles``), over the chunk and its
    continuation: a chunk that passes a mover closely late in the horizon, where the constant-velocity
    prediction is least sure, is not safe.
    """
    if blocked_fallback not in BLOCKED_FALLBACKS:
        raise ValueError(f"blocked_fallback must be one of {BLOCKED_FALLBACKS}, got {blocked_fallback!r}")
    B, K, T = candidates.shape[:3]
    body = TeamBody(template, agent_radius, dt)  # the team the sequences move
    check = FootprintCheck(obstacles, body, obstacle_velocity, start, continuation, mover_uncertainty)
    floor = check.floor(margin)
    footprint = check.footprint
    pool = candidates
    clear, viable, end = footprint(candidates, floor)
    # The manoeuvres matter only where no sampled chunk is safe with its continuation (without an
    # escape_advantage): elsewhere none of them could be kept, so they are scored only if some
    # episode needs them (most replans then score 11 sequences, not 11 + the lattice).
    sure = (clear if viable is None else viable) >= floor
    if escape_advantage is not None or not sure.any(axis=1).all():
        lattice = ESCAPE_PRIMITIVES if primitives is None else np.asarray(primitives, dtype=np.float64)
        prim = np.broadcast_to(lattice[None, :, None, :], (B, len(lattice), T, 2))
        if blend is not None:
            prim = blend_replan(prim, *blend)
        prim_clear, prim_viable, prim_end = footprint(prim, floor)
        pool = np.concatenate([candidates, prim], axis=1)
        clear = np.concatenate([clear, prim_clear], axis=1)
        end = np.concatenate([end, prim_end], axis=1)
        if viable is not None:
            viable = np.concatenate([viable, prim_viable], axis=1)
    progress = cost_to_go_progress(
        obstacles, goal, end[..., :2], PROGRESS_WINDOW, progress_resolution, progress_bilinear
    )
    safe = clear >= floor
    strict = None if viable is None else viable >= floor
    if halt_lookahead:  # second preference: a chunk after which the team may stop
        open_rows = np.ones(B, bool) if strict is None else ~strict.any(axis=1)
        if open_rows.any():
            rows_at = np.flatnonzero(open_rows)
            halted = check.halted(pool[rows_at], halt_lookahead, rows_at)
            stays = safe[rows_at] & (halted >= floor[rows_at])
            safe[rows_at] = np.where(stays.any(axis=1, keepdims=True), stays, safe[rows_at])
    if strict is not None:  # a preference: where no candidate's continuation is safe, the chunks'
        safe = np.where(strict.any(axis=1, keepdims=True), strict, safe)
    sampled_safe = safe[:, :K].any(axis=1)
    allowed = safe.copy()
    if escape_advantage is None:
        allowed[:, K:] &= ~sampled_safe[:, None]  # primitives only when no sampled chunk is safe
        score = progress
    else:  # a primitive must beat the best safe sampled chunk by escape_advantage metres of progress
        score = progress - np.where(np.arange(pool.shape[1]) >= K, escape_advantage, 0.0)[None, :]
    if coherence is not None:  # ranks only: info["progress"] stays the cost-to-go progress
        score = score - coherence.penalty(pool)
    best = np.argmax(np.where(allowed, score, -np.inf), axis=1)
    rows = np.arange(B)
    blocked = ~allowed.any(axis=1)
    stopped = np.zeros(B, dtype=bool)
    if blocked_fallback == "widest":
        fallback = np.argmax(clear if fallback_all else clear[:, :K], axis=1)  # a filter brakes
    else:  # the widest of all if it predicts no contact, else stop
        fallback = np.argmax(clear, axis=1)
        stopped = blocked & (clear[rows, fallback] < 0.0)
    choice = np.where(blocked, fallback, best)
    chosen = pool[rows, choice]
    chosen[stopped] = 0.0
    info = {
        "choice": choice,
        "clearance": clear[:, :K],
        "progress": progress[:, :K],
        "safe": safe[:, :K],
        "any_safe": sampled_safe,
        "escaped": (choice >= K) & ~stopped,
        "stopped": stopped,
        "blocked": blocked,
    }
    return chosen, info


def progress_goal(goal: np.ndarray, window: float = PROGRESS_WINDOW) -> np.ndarray:
    """The goal (B, 2) the progress grid is built around: beyond +-``window`` m, that square's point in
    the goal's direction (``cost_to_go_progress``)."""
    reach = np.abs(goal).max(axis=-1)
    return goal * np.minimum(1.0, window / np.maximum(reach, 1e-9))[:, None]


def cost_to_go_progress(
    obstacles: np.ndarray,
    goal: np.ndarray,
    end: np.ndarray,
    window: float,
    resolution: float = 0.2,
    bilinear: bool = False,
) -> np.ndarray:
    """Decrease (B, K) of a grid cost-to-go from the midpoint (the origin) to each candidate's end point
    (B, K, 2), in the body frame around the observed obstacles.

    Straight-line progress is greedy: it keeps the candidate that heads at the goal through an obstacle
    until every candidate collides, and drops the ones that start to go round it. The cost-to-go
    (``navigation.cost_to_go``, cells within 0.9 m of an obstacle three times dearer, as MPPI's goal
    cost) is the length of the way round. A goal beyond +-``window`` m is replaced by that square's
    point in the goal's direction, and the grid is fixed at +-(``window`` + 2) m (the goal's 2 m margin
    of ``navigation.cost_to_go`` included), so one episode's scores never depend on the other episodes
    of a batch: ``select_action`` at B = 1 scores as the batched engine does. Only the start and the end
    cells are read, so the wavefront stops as soon as they are exact (``navigation.cost_to_go_at``).
    ``resolution``: the cell size [m]; ``bilinear``: each point reads the four cells around it
    (``navigation``'s docstring), else its nearest cell. Nearest reads make progress a staircase with
    steps of a cell: candidates whose ends share a cell tie, and at each cell border the ranking
    jumps; the best-of-K choice then flips from replan to replan, which shows in the jerk (level3's
    first 100 tuning scenes: jerk 0.766 with nearest reads on 0.2 m cells, 0.909 on 0.3 m, 0.689 and
    0.666 with bilinear reads on 0.3 and 0.4 m).
    """
    B, K = end.shape[:2]
    g = progress_goal(goal, window)
    points = np.concatenate([np.zeros((B, 1, 2)), end], axis=1).reshape(B * (K + 1), 2)
    ctg = cost_to_go_at(
        obstacles,
        g,
        points,
        rows=np.repeat(np.arange(B), K + 1),
        inflate=PROGRESS_INFLATE,
        resolution=resolution,
        wall_cost=PROGRESS_WALL_COST,
        bounds=(-window - 2.0, window + 2.0),
        bilinear=bilinear,
    ).reshape(B, K + 1)
    return ctg[:, :1] - ctg[:, 1:]


def barrier_rows(
    obstacles: np.ndarray,
    template: np.ndarray,
    agent_radius: float | np.ndarray,
    margin: float,
    rate: float,
    obstacle_velocity: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CBF rows A u >= b of every agent-obstacle pair: A (B, N*M, 2), b (B, N*M), h (B, N*M); with
    ``obstacle_velocity`` (B, M, 2), b gains n . v_j (module docstring). ``agent_radius``: one radius
    or one per template agent (N,)."""
    B, M, _ = obstacles.shape
    d = template[None, :, None, :] - obstacles[:, None, :, :2]  # (B, N, M, 2), from obstacle to agent
    dist = np.maximum(np.linalg.norm(d, axis=-1), 1e-9)
    n = d / dist[..., None]
    radius = np.asarray(agent_radius, np.float64).reshape(1, -1, 1)  # one, or one per agent
    h = dist - obstacles[:, None, :, 2] - radius - margin
    bx, by = template[:, 0][None, :, None], template[:, 1][None, :, None]
    a_v = n[..., 1]
    a_w = -n[..., 0] * by + n[..., 1] * bx
    A = np.stack([a_v, a_w], axis=-1).reshape(B, -1, 2)
    h = h.reshape(B, -1)
    b = -rate * h
    if obstacle_velocity is not None:  # dh/dt = n . (p_i' - v_j)
        b = b + (n * obstacle_velocity[:, None]).sum(-1).reshape(B, -1)
    return A, b, h


def cbf_filter(
    action: np.ndarray,
    obstacles: np.ndarray,
    template: np.ndarray,
    agent_radius: float | np.ndarray,
    margin: float,
    rate: float,
    low: np.ndarray,
    high: np.ndarray,
    max_rows: int = 8,
    obstacle_velocity: np.ndarray | None = None,
    start: ChunkStart | None = None,
    dt: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """Filtered actions (B, 2) and whether the filter changed them (B,) (see the module docstring).

    Only the ``max_rows`` most critical agent-obstacle pairs (smallest h) enter the QP; a pair with
    alpha h above the largest |A u| any action can reach can never be active. ``obstacle_velocity``
    (B, M, 2): the obstacles' velocities (None: static). ``start`` (``predict_start``): the barrier
    is taken at the pose where the action will run, after the commands in flight (``dt`` their
    step), with the obstacles moved on to then; with rate limits the action box is the part of
    [low, high] reachable in one step from ``start.velocity``.
    """
    low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
    u0 = np.clip(np.asarray(action, dtype=np.float64), low, high)  # the env clips to the box anyway
    B = len(u0)
    box_low, box_high = low, high
    nominal = u0
    if start is not None:
        obstacles, obstacle_velocity = obstacles_at_start(obstacles, obstacle_velocity, start, dt)
        reach = np.array([start.max_linear_accel or np.inf, start.max_angular_accel or np.inf]) * dt
        box_low = np.clip(start.velocity - reach, low, high)  # (B, 2)
        box_high = np.clip(start.velocity + reach, low, high)
        nominal = np.clip(u0, box_low, box_high)  # what the actuator runs of u0
    A, b, h = barrier_rows(obstacles, template, agent_radius, margin, rate, obstacle_velocity)
    R = min(max_rows, A.shape[1])
    idx = np.argsort(h, axis=1)[:, :R]
    A = np.take_along_axis(A, idx[..., None], axis=1)
    b = np.take_along_axis(b, idx, axis=1)
    box_A = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    box_b = np.stack([box_low[..., 0], -box_high[..., 0], box_low[..., 1], -box_high[..., 1]], axis=-1)
    A = np.concatenate([A, np.broadcast_to(box_A, (B, 4, 2))], axis=1)  # (B, L, 2)
    b = np.concatenate([b, np.broadcast_to(box_b, (B, 4))], axis=1)  # (B, L)
    L = A.shape[1]
    w_inv = (high - low) ** 2  # W^-1: the metric is in units of the action ranges
    # candidates: the nominal action, its projection onto every line, every vertex of two lines
    Aw = A * w_inv
    t = (b - np.einsum("bld,bd->bl", A, nominal)) / np.maximum(np.einsum("bld,bld->bl", A, Aw), 1e-12)
    proj = nominal[:, None, :] + t[..., None] * Aw  # (B, L, 2)
    i, j = np.triu_indices(L, k=1)
    a1, a2, b1, b2 = A[:, i], A[:, j], b[:, i], b[:, j]
    det = a1[..., 0] * a2[..., 1] - a1[..., 1] * a2[..., 0]
    ok = np.abs(det) > 1e-9
    det = np.where(ok, det, 1.0)
    vx = (b1 * a2[..., 1] - b2 * a1[..., 1]) / det
    vy = (a1[..., 0] * b2 - a2[..., 0] * b1) / det
    vert = np.stack([vx, vy], axis=-1)
    vert = np.where(ok[..., None], vert, nominal[:, None, :])
    cand = np.concatenate([nominal[:, None, :], proj, vert], axis=1)  # (B, C, 2)
    slack = np.einsum("bld,bcd->bcl", A, cand) - b[:, None, :]  # (B, C, L), >= 0 where satisfied
    violation = np.maximum(-slack, 0.0).max(axis=-1)  # (B, C)
    cost = (((cand - nominal[:, None, :]) ** 2) / w_inv).sum(-1)
    feasible = violation <= 1e-9
    score = np.where(feasible, cost, np.inf)
    best = np.argmin(score, axis=1)
    least_bad = np.argmin(violation + 1e-6 * cost, axis=1)
    pick = np.where(feasible.any(axis=1), best, least_bad)
    out = cand[np.arange(B), pick]
    out = np.clip(out, box_low, box_high)
    changed = np.abs(out - nominal).max(axis=-1) > 1e-6
    return np.where(changed[:, None], out, u0), changed
