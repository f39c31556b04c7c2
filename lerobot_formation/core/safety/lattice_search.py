"""Lattice search in space and time: the safety layer's own proposals, a beam search over held motion
primitives against the obstacles where they are predicted to be (NumPy only, batched over episodes).

The layer's other candidates (the network's samples, route pursuit's chunk, the escape manoeuvres)
are each one way ahead; where a mover comes towards the team the way out is often a composite one
(turn away, then run), which none of them holds. This search builds such paths in the midpoint's body
frame, from where the next command starts (``core.safety.filters.ChunkStart``), over the primitives

    u_p = [v, omega],  v in {0, 0.3, 0.6} m/s,  omega in {-1.5, -0.75, 0, 0.75, 1.5} rad/s,

each held for ``PRIMITIVE_STEPS`` control steps (0.5 s). A path of d primitives is a node at time
t_d = d * 0.5 s (plus the actuator's delay); a child appends one primitive and is kept only if the
formation footprint stays at least the floor f clear of every obstacle over its steps, obstacle j
at its predicted place c_j + v_j t with its radius grown by u t (the layer's ``mover_uncertainty``;
``core.controllers.footprint.step_clearances``): the time-indexed safe-interval test of SIPP (Phillips
and Likhachev 2011, "SIPP: Safe Interval Path Planning for Dynamic Environments") on a state lattice
of motion primitives (Pivtoraiko and Kelly 2005). Each depth keeps, per cell of (x, y, heading) of
``CELL``, the child of least cost-to-go h at its end (the grid cost-to-go around the observed obstacles
that the layer's progress reads: ``core.world.navigation.cost_to_go`` with ``filters``' settings), and
of those the ``BEAM`` best:

    beam_{d+1} = best_BEAM { argmin_{children in cell} h(end) : cell }.

After ``DEPTH`` primitives (3 s; or the deepest depth a path survived to), the ``ways`` proposals are
the best path of each of the ``ways`` best first primitives (different ways out, not one way and its
near copies), cut to the chunk's length T. They join the candidates and are checked and scored like
every other (``core.safety.filters.select_chunk``): the search proposes, it never decides. It ignores
the actuator's rate limits (the check does not: a proposal that relies on an instant turn fails it).
"""

from __future__ import annotations

import numpy as np

from lerobot_formation.core.controllers.footprint import step_clearances
from lerobot_formation.core.safety.filters import (
    PROGRESS_INFLATE,
    PROGRESS_RESOLUTION,
    PROGRESS_WALL_COST,
    PROGRESS_WINDOW,
    FootprintCheck,
    progress_goal,
)
from lerobot_formation.core.world.navigation import cost_to_go

PRIMITIVES = np.array(
    [[v, w] for v in (0.0, 0.3, 0.6) for w in (-1.5, -0.75, 0.0, 0.75, 1.5)], dtype=np.float64
)  # [m/s, rad/s]
PRIMITIVES.flags.writeable = False
PRIMITIVE_STEPS = 5  # control steps a primitive is held (0.5 s)
DEPTH = 6  # primitives per path (3 s)
BEAM = 16  # paths kept per depth
CELL = (0.25, np.pi / 4)  # [m, rad] the cells that tell paths apart


def search_proposals(
    check: FootprintCheck, goal: np.ndarray, margin: float, steps: int, ways: int
) -> np.ndarray:
    """The proposals (B, ``ways``, ``steps``, 2) [m/s, rad/s] of the search (module docstring) for the
    episodes of ``check`` (its obstacles, their velocities, the start and the team's body), ``goal``
    (B, 2) in the body frame and the layer's ``margin`` (its floor: ``FootprintCheck.floor``). A row
    where no path survives its first primitive gets standing commands; one with fewer than ``ways``
    openings repeats its best path."""
    if ways < 1 or steps < 1:
        raise ValueError(f"search_proposals needs ways >= 1 and steps >= 1, got {ways} and {steps}")
    pose0, delay = check._origin()
    B = len(pose0)
    floor = check.floor(margin)  # (B, 1)
    field = cost_to_go(  # the grid the layer reads its progress on (``filters.cost_to_go_progress``)
        check.obstacles,
        progress_goal(goal),
        inflate=PROGRESS_INFLATE,
        resolution=PROGRESS_RESOLUTION,
        wall_cost=PROGRESS_WALL_COST,
        bounds=(-PROGRESS_WINDOW - 2.0, PROGRESS_WINDOW + 2.0),
    )
    P, n, length = len(PRIMITIVES), PRIMITIVE_STEPS, DEPTH * PRIMITIVE_STEPS
    velocity = check.obstacle_velocity
    poses = np.array(pose0, dtype=np.float64)[:, None]  # (B, E, 3) the beam's ends
    alive = np.ones((B, 1), dtype=bool)
    paths = np.zeros((B, 1, 0, 2))  # (B, E, d n, 2)
    opening = np.zeros((B, 1), dtype=np.int64)  # each path's first primitive
    found = np.zeros((B, ways, length, 2))
    for d in range(DEPTH):
        E = poses.shape[1]
        held = np.broadcast_to(PRIMITIVES[None, :, None, :], (B * E, P, n, 2))
        clear, rolled = step_clearances(
            poses.reshape(B * E, 3),
            held,
            np.repeat(check.obstacles, E, axis=0),
            check.body,
            None if velocity is None else np.repeat(velocity, E, axis=0),
            delay + d * n,
            check.mover_uncertainty,
        )
        ok = (clear.min(axis=-1).reshape(B, E, P) >= floor[:, :, None]) & alive[:, :, None]
        ends = rolled[:, :, -1].reshape(B, E * P, 3)
        h = field.at(ends[..., :2].reshape(-1, 2), np.repeat(np.arange(B), E * P), bilinear=True)
        score = np.where(ok.reshape(B, E * P), h.reshape(B, E * P), np.inf)
        keep = best_per_key(_cells(ends), score, BEAM)
        if not keep.any():
            break
        W = int(keep.sum(axis=1).max())
        chosen = np.argsort(~keep, axis=1, kind="stable")[:, :W]  # the kept children first
        alive = np.take_along_axis(keep, chosen, axis=1)
        parent, primitive = chosen // P, chosen % P
        paths = np.concatenate(
            [
                np.take_along_axis(paths, parent[..., None, None], axis=1),
                np.broadcast_to(PRIMITIVES[primitive][:, :, None, :], (B, W, n, 2)),
            ],
            axis=2,
        )
        poses = np.take_along_axis(ends, chosen[..., None], axis=1)
        opening = primitive if d == 0 else np.take_along_axis(opening, parent, axis=1)
        # each row with a survivor: the best path of each of its ``ways`` best openings so far
        scored = np.where(alive, np.take_along_axis(score, chosen, axis=1), np.inf)
        best = best_per_key(opening, scored, ways)
        ranked = np.argsort(np.where(best, scored, np.inf), axis=1, kind="stable")[:, :ways]
        ranked = np.where(np.take_along_axis(best, ranked, axis=1), ranked, ranked[:, :1])
        picked = np.take_along_axis(paths, ranked[..., None, None], axis=1)  # (B, ways', (d+1) n, 2)
        if picked.shape[1] < ways:
            picked = np.concatenate([picked, np.repeat(picked[:, :1], ways - picked.shape[1], axis=1)], 1)
        held_on = np.repeat(picked[:, :, -1:], length - picked.shape[2], axis=2)  # the last one held
        has = alive.any(axis=1)
        found[has] = np.concatenate([picked, held_on], axis=2)[has]
    return found[:, :, :steps] if steps <= length else _pad(found, steps)


def _pad(paths: np.ndarray, steps: int) -> np.ndarray:
    return np.concatenate([paths, np.repeat(paths[:, :, -1:], steps - paths.shape[2], axis=2)], axis=2)


def _cells(ends: np.ndarray) -> np.ndarray:
    """(B, C) one integer per cell of ``CELL`` of end poses (B, C, 3)."""
    i = np.floor(ends[..., 0] / CELL[0]).astype(np.int64)
    j = np.floor(ends[..., 1] / CELL[0]).astype(np.int64)
    k = np.floor(np.mod(ends[..., 2], 2 * np.pi) / CELL[1]).astype(np.int64)
    return (i * 4_099 + j) * 16 + k  # |i|, |j| < 2_048 within the field; 8 headings


def best_per_key(key: np.ndarray, score: np.ndarray, count: int) -> np.ndarray:
    """(B, C) bool: in each row, of its entries with a finite score the best of each ``key`` (ties: the
    first), and of those the ``count`` best."""
    B, C = key.shape
    finite = np.isfinite(score)
    row = np.repeat(np.arange(B), C)
    flat_key, flat_score = key.ravel(), score.ravel()
    order = np.lexsort((flat_score, flat_key, row))  # by row, then key, then score (stable)
    first = np.ones(len(order), dtype=bool)
    first[1:] = (row[order][1:] != row[order][:-1]) | (flat_key[order][1:] != flat_key[order][:-1])
    best = np.zeros(B * C, dtype=bool)
    best[order[first]] = True
    ranked = np.where(best.reshape(B, C) & finite, score, np.inf)
    top = np.argsort(ranked, axis=1, kind="stable")[:, :count]
    keep = np.zeros((B, C), dtype=bool)
    np.put_along_axis(keep, top, np.isfinite(np.take_along_axis(ranked, top, axis=1)), axis=1)
    return keep
