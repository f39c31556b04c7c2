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

from lerobot_formation.core.geometry import xy_clearance
from lerobot_formation.core.navigation import CostToGo


def rollout_poses(pose: np.ndarray, actions: np.ndarray, dt: float) -> np.ndarray:
    """Midpoint poses after each action, pose (B, 3), actions (B, C, T, 2) -> (B, C, T, 3) (Euler)."""
    B, C, T, _ = actions.shape
    v, w = actions[..., 0], actions[..., 1]
    phi = pose[:, 2][:, None, None] + np.cumsum(w, axis=-1) * dt  # heading after step k
    phi_before = np.concatenate(
        [np.broadcast_to(pose[:, 2][:, None, None], (B, C, 1)), phi[..., :-1]], axis=-1
    )
    x = pose[:, 0][:, None, None] + np.cumsum(v * np.cos(phi_before), axis=-1) * dt
    y = pose[:, 1][:, None, None] + np.cumsum(v * np.sin(phi_before), axis=-1) * dt
    return np.stack([x, y, phi], axis=-1)


def sequence_clearance(
    pose: np.ndarray,
    actions: np.ndarray,
    obstacles: np.ndarray,
    template: np.ndarray,
    dt: float,
    agent_radius: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Smallest predicted agent clearance (B, C) and end poses (B, C, 3) of candidate sequences."""
    B, C, T, _ = actions.shape
    poses = rollout_poses(pose, actions, dt)
    c, s = np.sin(poses[..., 2])[..., None], -np.cos(poses[..., 2])[..., None]  # rotation by phi - pi/2
    bx, by = template[:, 0], template[:, 1]
    ax = poses[..., 0][..., None] + bx * c - by * s  # (B, C, T, N)
    ay = poses[..., 1][..., None] + bx * s + by * c
    clear = xy_clearance(ax.reshape(B, -1), ay.reshape(B, -1), obstacles) - agent_radius
    return clear.reshape(B, C, -1).min(axis=-1), poses[:, :, -1]


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
