"""Clearance guidance: the gradient of a barrier cost on the whole formation's footprint with respect
to a command sequence, for steering a diffusion sampler away from the obstacles it observes.

Cost guidance of diffusion planners (Janner et al. 2022, "Planning with Diffusion for Flexible
Behavior Synthesis"; Carvalho et al. 2023, "Motion Planning Diffusion"): at each denoising step the
sampler's estimate of the clean chunk x0 moves down the gradient of a cost, and the step goes on from
the moved estimate. Here the cost is what the safety layer checks afterwards, made smooth.

Model (``dynamics.rollout_poses``): from a pose (x_0, y_0, phi_0), command k = 1..T, [v_k, w_k], gives

    phi_k = phi_{k-1} + w_k dt,   x_k = x_{k-1} + v_k cos(phi_{k-1}) dt,   y_k = y_{k-1} + v_k sin(phi_{k-1}) dt.

Agent i of the rigid template (body offset (a_i, b_i)) then sits at (``dynamics.body_to_world``)

    X_ik = x_k + a_i sin(phi_k) + b_i cos(phi_k),   Y_ik = y_k - a_i cos(phi_k) + b_i sin(phi_k),

and its clearance to obstacle j (centre c_jk at that step, radius r_j; a mover at constant velocity)
is d_ijk = |(X_ik, Y_ik) - c_jk| - r_j - r_agent. The cost, with the guidance distance delta,

    J = sum_k sum_i sum_j 0.5 max(0, delta - d_ijk)^2,

is zero for a chunk that keeps delta from everything, and grows with the depth of every intrusion.
Its gradient through the rollout (reverse cumulative sums, no autograd): with g^x_k, g^y_k, g^phi_k
the partial derivatives of J at pose k, G_k = sum_{m >= k} g_m,

    dJ/dv_k = dt (cos(phi_{k-1}) G^x_k + sin(phi_{k-1}) G^y_k),
    dJ/dw_k = dt G^phi_k + dt^2 sum_{l > k} v_l (-sin(phi_{l-1}) G^x_l + cos(phi_{l-1}) G^y_l).

The actuator's rate limits are left out of the gradient (the commands are taken as executed); the
safety layer's checks after sampling are exact.
"""

from __future__ import annotations

import numpy as np

from lerobot_formation.core.controllers.footprint import TeamBody, obstacles_along
from lerobot_formation.core.world.dynamics import rollout_poses


def clearance_cost_gradient(
    pose: np.ndarray,
    actions: np.ndarray,
    obstacles: np.ndarray,
    body: TeamBody,
    distance: float,
    obstacle_velocity: np.ndarray | None = None,
    start_step: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """The cost J (B, C) of the module docstring and its gradient dJ/d actions (B, C, T, 2).

    Args:
        pose: (B, 3) where the sequences start (the midpoint in the body frame, or the actuator's
            predicted start, ``core.safety.filters.ChunkStart.pose``).
        actions: (B, C, T, 2) [v, omega] command sequences, C per start.
        obstacles: (B, M, 3) [x, y, r] in the same frame (an absent slot: far away, radius 0).
        body: the team (``footprint.TeamBody``): its template (N, 2) of the agents' body offsets
            (a_i, b_i), their radius r_agent [m] (one, or one per template agent (N,)) and the
            control step dt [s].
        distance: delta [m], the clearance below which J grows.
        obstacle_velocity: (B, M, 2) constant velocities (None: static); pose k is checked against
            the obstacles at time (``start_step`` + k) dt.
    """
    if not distance > 0:
        raise ValueError(f"the guidance distance must be > 0 [m], got {distance!r}")
    B, C, T, _ = actions.shape
    dt = body.dt
    poses = rollout_poses(pose, actions, dt)  # (B, C, T, 3) after each command
    x, y, phi = poses[..., 0], poses[..., 1], poses[..., 2]
    if obstacle_velocity is None:
        centres = obstacles[:, None, None]  # (B, 1, 1, M, 3)
    else:
        centres = obstacles_along(obstacles, obstacle_velocity, T, dt, start_step)[:, None]  # (B, 1, T, M, 3)
    template = np.asarray(body.template, dtype=np.float64)
    N = len(template)
    radii = np.broadcast_to(np.asarray(body.agent_radius, dtype=np.float64), (N,)).reshape(N, 1, 1, 1, 1)
    a, b = template[:, 0].reshape(N, 1, 1, 1), template[:, 1].reshape(N, 1, 1, 1)
    s, c = np.sin(phi), np.cos(phi)
    ax, ay = x + a * s + b * c, y - a * c + b * s  # body_to_world, every agent at once: (N, B, C, T)
    dx = ax[..., None] - centres[..., 0]  # (N, B, C, T, M)
    dy = ay[..., None] - centres[..., 1]
    norm = np.maximum(np.sqrt(dx * dx + dy * dy), 1e-9)
    depth = np.maximum(0.0, distance - (norm - centres[..., 2] - radii))
    cost = 0.5 * (depth * depth).sum(axis=(0, -1, -2))
    # dJ/d(agent position) = -depth * the unit vector away from the obstacle, summed over obstacles
    scale = depth / norm
    px, py = -(scale * dx).sum(-1), -(scale * dy).sum(-1)  # (N, B, C, T)
    gx, gy = px.sum(0), py.sum(0)
    gphi = (px * (a * c - b * s) + py * (a * s + b * c)).sum(0)  # d(X, Y)/dphi of body_to_world
    rev = lambda g: np.cumsum(g[..., ::-1], axis=-1)[..., ::-1]  # noqa: E731  G_k = sum_{m >= k} g_m
    Gx, Gy, Gphi = rev(gx), rev(gy), rev(gphi)
    phi_before = np.concatenate([np.broadcast_to(pose[:, 2][:, None, None], (B, C, 1)), phi[..., :-1]], -1)
    sb, cb = np.sin(phi_before), np.cos(phi_before)
    grad = np.empty_like(actions, dtype=np.float64)
    grad[..., 0] = dt * (cb * Gx + sb * Gy)
    h = actions[..., 0] * (-sb * Gx + cb * Gy)  # (B, C, T): v_l (...) at l
    later = np.concatenate([rev(h)[..., 1:], np.zeros((B, C, 1))], axis=-1)  # sum over l > k
    grad[..., 1] = dt * Gphi + dt**2 * later
    return cost, grad
