"""Clearance and collision for all agents (SPEC "The world": any agent disc touching any obstacle)."""

from __future__ import annotations

import numpy as np

# Padded obstacle rows sit at (1e6, 1e6) with radius 0 (core.world.scenes.FAR), so a clearance this large
# means "no obstacle": scenes keep start and goal within 50 m of the origin.
NO_OBSTACLE = 1.0e5  # [m]
# xy_clearance takes every obstacle slot at once up to this many point-obstacle pairs (~1 MB a temporary)
ALL_SLOTS_AT_ONCE = 1 << 17


def no_obstacle_as_inf(clearance: np.ndarray) -> np.ndarray:
    """Clearances with padding values (``>= NO_OBSTACLE``: the scene has no obstacle) set to +inf,
    the distance to the nearest of no obstacles. Metrics turn inf into NaN (null in JSON)."""
    clearance = np.asarray(clearance, dtype=np.float64)
    return np.where(clearance >= NO_OBSTACLE, np.inf, clearance)


def point_clearance(points: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
    """Distance from points (B, ..., 2) to the nearest obstacle surface, obstacles (B, M, 3) -> (B, ...).

    Padded obstacle rows sit far away with radius 0, so they never win the minimum.
    """
    B = points.shape[0]
    return xy_clearance(points[..., 0].reshape(B, -1), points[..., 1].reshape(B, -1), obstacles).reshape(
        points.shape[:-1]
    )


def xy_clearance(
    x: np.ndarray, y: np.ndarray, obstacles: np.ndarray, dtype=np.float64, min_axis: int | None = None
) -> np.ndarray:
    """Like ``point_clearance`` for coordinates given apart, x and y (..., B, P) -> (..., B, P). The hot
    path of the footprint checks (PAC, MPPI, candidate scoring).

    ``min_axis``: the smallest clearance over this axis of x and y (e.g. the agents of a footprint),
    taken on the squared distances before the square root: the same values as the minimum of the
    result, for fewer square roots. ``dtype=np.float32``: MPPI's fast path (inputs cast first).

    Up to ``ALL_SLOTS_AT_ONCE`` point-obstacle pairs, every obstacle slot is taken in one array
    operation (a replan's checks at B = 1: a few numpy calls instead of a few per slot); above it, one
    slot at a time, which avoids (M, ..., B, P) temporaries. Both give the same numbers.
    """
    x, y = np.asarray(x).astype(dtype, copy=False), np.asarray(y).astype(dtype, copy=False)
    obstacles = np.asarray(obstacles).astype(dtype, copy=False)
    M = obstacles.shape[1]
    if M == 0:
        shape = x.shape if min_axis is None else np.delete(x.shape, min_axis)
        return np.full(shape, np.inf)
    if x.size * M <= ALL_SLOTS_AT_ONCE:
        column = (M, *(1,) * (x.ndim - 2), len(obstacles), 1)  # slots first, against (..., B, P)
        dx = x - obstacles[..., 0].T.reshape(column)
        dy = y - obstacles[..., 1].T.reshape(column)
        d2, radius = dx * dx + dy * dy, obstacles[..., 2].T.reshape(column)
        if min_axis is not None:
            axis = min_axis + 1 if min_axis >= 0 else min_axis
            d2, radius = d2.min(axis=axis), radius.min(axis=axis)  # radius: a length-1 axis dropped
        return (np.sqrt(d2) - radius).min(axis=0)
    out = None
    for m in range(M):
        d2 = _squared_distance(x, y, obstacles[:, m])
        if min_axis is not None:
            d2 = d2.min(axis=min_axis)
        gap = np.sqrt(d2) - obstacles[:, m, 2][:, None]
        out = gap if out is None else np.minimum(out, gap, out=out)
    return out


def obstacle_gaps(points: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
    """Distance from points (B, P, 2) to each obstacle's surface, obstacles (B, M, 3) -> (B, P, M)
    (padded rows included: scene validity masks them itself)."""
    x, y = points[..., 0], points[..., 1]
    gaps = np.empty((*points.shape[:-1], obstacles.shape[1]))
    for m in range(obstacles.shape[1]):
        gaps[..., m] = np.sqrt(_squared_distance(x, y, obstacles[:, m])) - obstacles[:, m, 2][:, None]
    return gaps


def _squared_distance(x: np.ndarray, y: np.ndarray, obstacle: np.ndarray) -> np.ndarray:
    """Squared distance from points x, y (..., B, P) to the centres of one obstacle slot (B, 3)."""
    dx = x - obstacle[:, 0][:, None]
    dy = y - obstacle[:, 1][:, None]
    return dx * dx + dy * dy


def agent_clearances(positions: np.ndarray, obstacles: np.ndarray, agent_radius: float = 0.1) -> np.ndarray:
    """Gap between each agent disc and the nearest obstacle, positions (B, N, 2) -> (B, N).

    Negative means the disc overlaps an obstacle (a collision).
    """
    return point_clearance(positions, obstacles) - agent_radius


def midpoint_clearance(pose: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
    """Distance from the leaders' midpoint (B, 3) to the nearest obstacle surface -> (B,)."""
    return point_clearance(pose[:, None, :2], obstacles)[:, 0]
