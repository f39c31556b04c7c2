"""The learned planner's safety layer: best-of-K chunk selection and a control-barrier-function filter.

Everything here works in the midpoint's body frame (x right, y along the heading; the midpoint at the
origin, pose ``BODY_POSE``), which is what the egocentric ``nearest`` encoding observes, so the layer
needs nothing but the policy's own observation: no privileged state. The followers are assumed to sit
on their square slots (the formation template); they track them within ~0.1 m, which ``margin``
covers.

``select_chunk`` (best-of-K, the "safest" rule of adaptive sampling):
  1. roll each candidate chunk's whole horizon through the midpoint unicycle and place the rigid
     formation footprint (all four agents) at every step (``footprint.sequence_clearance``);
  2. discard candidates that come within ``margin`` of an obstacle (when the team is already inside
     the margin, those that come closer than it is now, minus 2 cm);
  3. among the rest keep the one with the most progress toward the goal: the decrease of a grid
     cost-to-go around the observed obstacles (``cost_to_go_progress``; straight-line progress is
     greedy and drives into obstacles, clearance alone would steer away from the goal too);
  4. if none is safe, a safe escape manoeuvre (a turn in place or a slow arc, ``ESCAPE_PRIMITIVES``)
     with the most progress; if none of those is safe either (``blocked_fallback``): "widest", the
     sampled candidate with the largest predicted clearance (a CBF filter then brakes); "stop", the
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
"""

from __future__ import annotations

import numpy as np

from lerobot_formation.core.footprint import sequence_clearance
from lerobot_formation.core.navigation import cost_to_go_at
from lerobot_formation.core.replan_blend import blend_replan
from lerobot_formation.core.scene import FAR

BODY_POSE = np.array([0.0, 0.0, np.pi / 2])  # the midpoint in its own body frame, facing +y


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
_ESCAPE_V = (0.0, 0.1, 0.2, 0.3)
_ESCAPE_OMEGA = (-1.5, -1.0, -0.5, -0.25, 0.0, 0.25, 0.5, 1.0, 1.5)
ESCAPE_PRIMITIVES = np.array([[v, w] for v in _ESCAPE_V for w in _ESCAPE_OMEGA if (v, w) != (0.0, 0.0)])


def select_chunk(
    candidates: np.ndarray,
    obstacles: np.ndarray,
    goal: np.ndarray,
    template: np.ndarray,
    dt: float,
    agent_radius: float,
    margin: float,
    progress_measure: str = "cost_to_go",
    window: float = 6.0,
    escape: bool = True,
    escape_advantage: float | None = None,
    blend: tuple[np.ndarray, np.ndarray, int] | None = None,
    blocked_fallback: str = "widest",
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The kept chunk (B, T, 2) [v, omega] among candidates (B, K, T, 2), and diagnostics.

    ``obstacles`` (B, M, 3) and ``goal`` (B, 2) are in the body frame. ``progress_measure``
    "cost_to_go" (default) or "euclidean" (see ``cost_to_go_progress``). With ``escape``, when no
    candidate is safe the safe ``ESCAPE_PRIMITIVES`` chunk with the most progress is kept, if any.
    With ``escape_advantage`` (metres), a safe primitive is also kept when its progress beats every
    safe sampled chunk's by that much: a team the policy keeps pressing against an obstacle (its
    chunks safe only because they barely move) goes round it instead of timing out there.
    ``info["choice"]`` is the kept index (K + j for primitive j). ``blend`` = (last executed action
    (B, 2), whether there is one (B,), m): the primitives are blended into the executed action as the
    caller blended the sampled chunks (``core.replan_blend``), so what is scored is what will run.
    ``blocked_fallback`` (step 4 of the module docstring): "widest" or "stop"; ``info["stopped"]`` says
    where the team stops.
    """
    if blocked_fallback not in BLOCKED_FALLBACKS:
        raise ValueError(f"blocked_fallback must be one of {BLOCKED_FALLBACKS}, got {blocked_fallback!r}")
    B, K, T = candidates.shape[:3]
    pool = candidates
    if escape:
        prim = np.broadcast_to(ESCAPE_PRIMITIVES[None, :, None, :], (B, len(ESCAPE_PRIMITIVES), T, 2))
        if blend is not None:
            prim = blend_replan(prim, *blend)
        pool = np.concatenate([candidates, prim], axis=1)
    pose = np.broadcast_to(BODY_POSE, (B, 3))
    clear, end = sequence_clearance(pose, pool, obstacles, template, dt, agent_radius)
    if progress_measure == "euclidean":
        dist0 = np.linalg.norm(goal, axis=-1)
        progress = dist0[:, None] - np.linalg.norm(goal[:, None, :] - end[..., :2], axis=-1)
    else:
        progress = cost_to_go_progress(obstacles, goal, end[..., :2], window)
    # inside the margin already (the filter holds the team at its edge): a chunk that gets no closer
    # than now counts as safe, so that the team may slide along an obstacle instead of stalling there
    now, _ = sequence_clearance(pose, np.zeros((B, 1, 1, 2)), obstacles, template, dt, agent_radius)
    safe = clear >= np.minimum(margin, now - SLIDE_TOLERANCE)
    sampled_safe = safe[:, :K].any(axis=1)
    allowed = safe.copy()
    if escape_advantage is None:
        allowed[:, K:] &= ~sampled_safe[:, None]  # primitives only when no sampled chunk is safe
        score = progress
    else:  # a primitive must beat the best safe sampled chunk by escape_advantage metres of progress
        score = progress - np.where(np.arange(pool.shape[1]) >= K, escape_advantage, 0.0)[None, :]
    best = np.argmax(np.where(allowed, score, -np.inf), axis=1)
    rows = np.arange(B)
    blocked = ~allowed.any(axis=1)
    stopped = np.zeros(B, dtype=bool)
    if blocked_fallback == "widest":
        fallback = np.argmax(clear[:, :K], axis=1)  # the widest sampled chunk (a filter brakes)
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
    }
    return chosen, info


def cost_to_go_progress(
    obstacles: np.ndarray, goal: np.ndarray, end: np.ndarray, window: float
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
    """
    B, K = end.shape[:2]
    reach = np.abs(goal).max(axis=-1)
    g = goal * np.minimum(1.0, window / np.maximum(reach, 1e-9))[:, None]
    points = np.concatenate([np.zeros((B, 1, 2)), end], axis=1).reshape(B * (K + 1), 2)
    ctg = cost_to_go_at(
        obstacles,
        g,
        points,
        rows=np.repeat(np.arange(B), K + 1),
        inflate=0.9,
        wall_cost=3.0,
        bounds=(-window - 2.0, window + 2.0),
    ).reshape(B, K + 1)
    return ctg[:, :1] - ctg[:, 1:]


def barrier_rows(
    obstacles: np.ndarray, template: np.ndarray, agent_radius: float, margin: float, rate: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CBF rows A u >= b of every agent-obstacle pair: A (B, N*M, 2), b (B, N*M), h (B, N*M)."""
    B, M, _ = obstacles.shape
    d = template[None, :, None, :] - obstacles[:, None, :, :2]  # (B, N, M, 2), from obstacle to agent
    dist = np.maximum(np.linalg.norm(d, axis=-1), 1e-9)
    n = d / dist[..., None]
    h = dist - obstacles[:, None, :, 2] - agent_radius - margin
    bx, by = template[:, 0][None, :, None], template[:, 1][None, :, None]
    a_v = n[..., 1]
    a_w = -n[..., 0] * by + n[..., 1] * bx
    A = np.stack([a_v, a_w], axis=-1).reshape(B, -1, 2)
    h = h.reshape(B, -1)
    return A, -rate * h, h


def cbf_filter(
    action: np.ndarray,
    obstacles: np.ndarray,
    template: np.ndarray,
    agent_radius: float,
    margin: float,
    rate: float,
    low: np.ndarray,
    high: np.ndarray,
    max_rows: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """Filtered actions (B, 2) and whether the filter changed them (B,) (see the module docstring).

    Only the ``max_rows`` most critical agent-obstacle pairs (smallest h) enter the QP; a pair with
    alpha h above the largest |A u| any action can reach can never be active.
    """
    low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
    u0 = np.clip(np.asarray(action, dtype=np.float64), low, high)  # the env clips to the box anyway
    B = len(u0)
    A, b, h = barrier_rows(obstacles, template, agent_radius, margin, rate)
    R = min(max_rows, A.shape[1])
    idx = np.argsort(h, axis=1)[:, :R]
    A = np.take_along_axis(A, idx[..., None], axis=1)
    b = np.take_along_axis(b, idx, axis=1)
    box_A = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    box_b = np.stack([low[0], -high[0], low[1], -high[1]])
    A = np.concatenate([A, np.broadcast_to(box_A, (B, 4, 2))], axis=1)  # (B, L, 2)
    b = np.concatenate([b, np.broadcast_to(box_b, (B, 4))], axis=1)  # (B, L)
    L = A.shape[1]
    w_inv = (high - low) ** 2  # W^-1: the metric is in units of the action ranges
    # candidates: u0, its projection onto every line, every vertex of two lines
    Aw = A * w_inv
    t = (b - np.einsum("bld,bd->bl", A, u0)) / np.maximum(np.einsum("bld,bld->bl", A, Aw), 1e-12)
    proj = u0[:, None, :] + t[..., None] * Aw  # (B, L, 2)
    i, j = np.triu_indices(L, k=1)
    a1, a2, b1, b2 = A[:, i], A[:, j], b[:, i], b[:, j]
    det = a1[..., 0] * a2[..., 1] - a1[..., 1] * a2[..., 0]
    ok = np.abs(det) > 1e-9
    det = np.where(ok, det, 1.0)
    vx = (b1 * a2[..., 1] - b2 * a1[..., 1]) / det
    vy = (a1[..., 0] * b2 - a2[..., 0] * b1) / det
    vert = np.stack([vx, vy], axis=-1)
    vert = np.where(ok[..., None], vert, u0[:, None, :])
    cand = np.concatenate([u0[:, None, :], proj, vert], axis=1)  # (B, C, 2)
    slack = np.einsum("bld,bcd->bcl", A, cand) - b[:, None, :]  # (B, C, L), >= 0 where satisfied
    violation = np.maximum(-slack, 0.0).max(axis=-1)  # (B, C)
    cost = (((cand - u0[:, None, :]) ** 2) / w_inv).sum(-1)
    feasible = violation <= 1e-9
    score = np.where(feasible, cost, np.inf)
    best = np.argmin(score, axis=1)
    least_bad = np.argmin(violation + 1e-6 * cost, axis=1)
    pick = np.where(feasible.any(axis=1), best, least_bad)
    out = cand[np.arange(B), pick]
    out = np.clip(out, low, high)
    changed = np.abs(out - u0).max(axis=-1) > 1e-6
    return np.where(changed[:, None], out, u0), changed
