"""Whole-formation footprint predictions for candidate action sequences, and the "safest" rule of
adaptive sampling.

``sequence_clearance`` rolls B x C action sequences (B, C, T, 2) through the midpoint unicycle and
places the rigid formation template (all four agents, followers at their square slots) at every
step; it returns each candidate's smallest agent clearance and its end pose. The followers are
assumed to sit on their slots: they track them within the formation-error floor (~0.05 m), which
``margin`` covers.

``select_safest`` is the adaptive policy's rule (the paper does not define "safest"):
  1. discard candidates whose footprint comes within ``margin`` of an obstacle (any agent, followers
     included: the square's rear corners swing out when the team turns);
  2. among the rest, prefer progress toward the goal: the largest decrease of the cost-to-go
     (grid shortest-path distance around inflated obstacles) from the start to the end of the
     rollout; plain clearance maximisation would steer away from everything, goal included;
  3. if every candidate collides, take the one with the largest predicted clearance.
"""

from __future__ import annotations

import numpy as np

from lerobot_formation.core.dynamics import body_to_world, rollout_poses
from lerobot_formation.core.geometry import xy_clearance
from lerobot_formation.core.navigation import CostToGo

__all__ = ["rollout_poses", "select_safest", "sequence_clearance", "template_clearance"]


def template_clearance(
    poses: np.ndarray, obstacles: np.ndarray, template: np.ndarray, agent_radius: float, dtype=np.float64
) -> np.ndarray:
    """Smallest agent-disc clearance of the rigid formation template placed at midpoint poses
    (B, ..., 3), obstacles (B, M, 3) -> (B, ...) float64: ``body_to_world`` + ``xy_clearance``.

    The one footprint check of PAC's governor, MPPI's cost and candidate scoring (``dtype=np.float32``:
    MPPI's fast path).
    """
    B, shape = poses.shape[0], poses.shape[:-1]
    x, y, phi = (poses[..., k].reshape(B, -1) for k in range(3))  # (B, P)
    column = (-1, 1, 1)  # template agents first: (N, 1, 1) against (B, P)
    ax, ay = body_to_world(template[:, 0].reshape(column), template[:, 1].reshape(column), x, y, phi, dtype)
    clear = xy_clearance(ax, ay, obstacles, dtype, min_axis=0)  # (B, P), nearest agent
    return (clear.astype(np.float64, copy=False) - agent_radius).reshape(shape)


def sequence_clearance(
    pose: np.ndarray,
    actions: np.ndarray,
    obstacles: np.ndarray,
    template: np.ndarray,
    dt: float,
    agent_radius: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Smallest predicted agent clearance (B, C) and end poses (B, C, 3) of candidate sequences."""
    poses = rollout_poses(pose, actions, dt)  # (B, C, T, 3)
    clear = template_clearance(poses, obstacles, template, agent_radius)
    return clear.min(axis=-1), poses[:, :, -1]


def select_safest(
    pose: np.ndarray,
    candidates: np.ndarray,
    obstacles: np.ndarray,
    ctg: CostToGo,
    template: np.ndarray,
    dt: float,
    agent_radius: float,
    margin: float = 0.05,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Index (B,) of the chosen candidate among (B, K, T, 2), and diagnostics."""
    B, K = candidates.shape[:2]
    clear, end = sequence_clearance(pose, candidates, obstacles, template, dt, agent_radius)
    start_cost = ctg.at(pose[:, :2])  # (B,)
    end_cost = ctg.at(end[..., :2].reshape(B * K, 2), rows=np.repeat(np.arange(B), K))
    progress = start_cost[:, None] - end_cost.reshape(B, K)
    safe = clear >= margin
    score = np.where(safe, progress, -np.inf)
    best = np.argmax(score, axis=1)
    fallback = np.argmax(clear, axis=1)
    choice = np.where(safe.any(axis=1), best, fallback)
    return choice, {"clearance": clear, "progress": progress, "safe": safe}
