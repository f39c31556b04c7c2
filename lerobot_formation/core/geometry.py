"""Clearance and collision for all agents (SPEC "The world": any agent disc touching any obstacle)."""

from __future__ import annotations

import numpy as np

# Padded obstacle rows sit at (1e6, 1e6) with radius 0 (core.scene.FAR), so a clearance this large
# means "no obstacle": scenes keep start and goal within 50 m of the origin.
NO_OBSTACLE = 1.0e5  # [m]


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


def xy_clearance(x: np.ndarray, y: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
    """Like ``point_clearance`` for coordinates given apart, x and y (B, P) -> (B, P). The hot path of
    PAC's and MPPI's footprint checks: one obstacle slot at a time avoids (B, P, M, 2) temporaries."""
    out = None
    for m in range(obstacles.shape[1]):
        dx = x - obstacles[:, m, 0][:, None]
        dy = y - obstacles[:, m, 1][:, None]
        gap = np.sqrt(dx * dx + dy * dy) - obstacles[:, m, 2][:, None]
        out = gap if out is None else np.minimum(out, gap, out=out)
    if out is None:
        return np.full(x.shape, np.inf)
    return out


def agent_clearances(positions: np.ndarray, obstacles: np.ndarray, agent_radius: float = 0.1) -> np.ndarray:
    """Gap between each agent disc and the nearest obstacle, positions (B, N, 2) -> (B, N).

    Negative means the disc overlaps an obstacle (a collision).
    """
    return point_clearance(positions, obstacles) - agent_radius


def midpoint_clearance(pose: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
    """Distance from the leaders' midpoint (B, 3) to the nearest obstacle surface -> (B,)."""
    return point_clearance(pose[:, None, :2], obstacles)[:, 0]
