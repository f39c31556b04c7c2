"""Clearance and collision for all agents (SPEC "The world": any agent disc touching any obstacle)."""

from __future__ import annotations

import numpy as np


def point_clearance(points: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
    """Distance from points (B, ..., 2) to the nearest obstacle surface, obstacles (B, M, 3) -> (B, ...).

    Padded obstacle rows sit far away with radius 0, so they never win the minimum.
    """
    B = points.shape[0]
    pts = points.reshape(B, -1, 1, 2)
    d = pts - obstacles[:, None, :, :2]
    gap = np.sqrt(np.sum(d * d, axis=-1)) - obstacles[:, None, :, 2]  # (B, P, M)
    return np.min(gap, axis=-1).reshape(points.shape[:-1])


def agent_clearances(positions: np.ndarray, obstacles: np.ndarray, agent_radius: float = 0.1) -> np.ndarray:
    """Gap between each agent disc and the nearest obstacle, positions (B, N, 2) -> (B, N).

    Negative means the disc overlaps an obstacle (a collision).
    """
    return point_clearance(positions, obstacles) - agent_radius


def midpoint_clearance(pose: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
    """Distance from the leaders' midpoint (B, 3) to the nearest obstacle surface -> (B,)."""
    return point_clearance(pose[:, None, :2], obstacles)[:, 0]
