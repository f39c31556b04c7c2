"""Whole-formation footprint predictions for candidate action sequences.

``sequence_clearance`` rolls B x C action sequences (B, C, T, 2) through the midpoint unicycle and
places the rigid formation template (all four agents, followers at their square slots) at every
step; it returns each candidate's smallest agent clearance and its end pose. The team it rolls out
is a ``TeamBody``: the template, the agents' radius and the control step. The followers are
assumed to sit on their slots: they track them within the formation-error floor (~0.05 m), which
``margin`` covers.

The best-of-K scorer that uses them is ``core.safety.filters.select_chunk``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lerobot_formation.core.perception.obstacle_tracker import predict_obstacles
from lerobot_formation.core.world.dynamics import FormationParams, body_to_world, rollout_poses
from lerobot_formation.core.world.geometry import xy_clearance

__all__ = [
    "TeamBody",
    "obstacles_along",
    "rollout_poses",
    "sequence_clearance",
    "step_clearances",
    "template_clearance",
]


@dataclass(frozen=True)
class TeamBody:
    """The team's body as the footprint checks see it: what a command sequence moves and what must
    keep clear of the obstacles (``sequence_clearance``, ``core.safety.guidance``, the safety layer's
    checks).

    Attributes:
        template: (N, 2) the rigid formation's agent offsets in the midpoint's body frame (the
            followers on their slots).
        agent_radius: [m] one radius for every agent, or one per template agent (N,) (e.g. the safety
            layer's followers with an allowance for how far they lag their slots).
        dt: [s] the control step: each command of a sequence acts for dt.
    """

    template: np.ndarray
    agent_radius: float | np.ndarray
    dt: float

    @classmethod
    def of(cls, params: FormationParams) -> TeamBody:
        """The body of the team ``params`` describes: its graph's template, agent radius and step."""
        return cls(np.asarray(params.graph.template), params.agent_radius, params.dt)


def template_clearance(
    poses: np.ndarray,
    obstacles: np.ndarray,
    template: np.ndarray,
    agent_radius: float | np.ndarray,
    dtype=np.float64,
) -> np.ndarray:
    """Smallest agent-disc clearance of the rigid formation template placed at midpoint poses
    (B, ..., 3), obstacles (B, M, 3) -> (B, ...) float64: ``body_to_world`` + ``xy_clearance``.
    ``agent_radius``: one radius, or one per template agent (N,) (e.g. the safety layer's followers
    with an allowance for how far they lag their slots).

    The one footprint check of PAC's governor, MPPI's cost and candidate scoring (``dtype=np.float32``:
    MPPI's fast path).
    """
    B, shape = poses.shape[0], poses.shape[:-1]
    x, y, phi = (poses[..., k].reshape(B, -1) for k in range(3))  # (B, P)
    column = (-1, 1, 1)  # template agents first: (N, 1, 1) against (B, P)
    ax, ay = body_to_world(template[:, 0].reshape(column), template[:, 1].reshape(column), x, y, phi, dtype)
    if np.ndim(agent_radius) == 0:
        clear = xy_clearance(ax, ay, obstacles, dtype, min_axis=0)  # (B, P), nearest agent
        return (clear.astype(np.float64, copy=False) - agent_radius).reshape(shape)
    radius = np.asarray(agent_radius, np.float64)
    if radius.shape != (len(template),):
        raise ValueError(
            f"agent_radius must be a number or one per template agent {len(template)}, got {radius.shape}"
        )
    clear = None
    for r in np.unique(radius):  # the agents of one radius together: as few square roots as above
        group = radius == r
        gap = xy_clearance(ax[group], ay[group], obstacles, dtype, min_axis=0).astype(np.float64) - r
        clear = gap if clear is None else np.minimum(clear, gap)
    return clear.reshape(shape)


def obstacles_along(
    obstacles: np.ndarray,
    velocity: np.ndarray,
    steps: int,
    dt: float,
    start_step: int = 0,
    uncertainty: float = 0.0,
) -> np.ndarray:
    """Obstacles (B, M, 3) at constant velocity (B, M, 2) where pose k = 1..``steps`` of a sequence
    meets them, at time (``start_step`` + k) dt -> (B, steps, M, 3) (``predict_obstacles``)."""
    times = (start_step + 1 + np.arange(steps)) * dt
    return predict_obstacles(obstacles, velocity, times, uncertainty)


def step_clearances(
    pose: np.ndarray,
    actions: np.ndarray,
    obstacles: np.ndarray,
    body: TeamBody,
    obstacle_velocity: np.ndarray | None = None,
    start_step: int = 0,
    mover_uncertainty: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Predicted agent clearance after every action (B, C, T) and the poses (B, C, T, 3) of the team's
    ``body`` moved by candidate sequences ``actions`` (B, C, T, 2) [v, omega] from ``pose`` (B, 3),
    among ``obstacles`` (B, M, 3).

    ``obstacle_velocity`` (B, M, 2): the obstacles move at constant velocity, and the pose after
    action k is checked against them at time (``start_step`` + k + 1) dt (``start_step``: the steps
    from now until the first action runs). None: they stand still (the same numbers as all zeros).
    ``mover_uncertainty`` [m/s]: a moving obstacle's predicted radius grows by that much per second
    ahead (``obstacle_tracker.predict_obstacles``).
    """
    poses = rollout_poses(pose, actions, body.dt)  # (B, C, T, 3)
    if obstacle_velocity is None:
        clear = template_clearance(poses, obstacles, body.template, body.agent_radius)
    else:  # time folded into the batch: step k's poses against the obstacles at step k
        B, C, T, _ = poses.shape
        moved = obstacles_along(obstacles, obstacle_velocity, T, body.dt, start_step, mover_uncertainty)
        at = np.ascontiguousarray(poses.transpose(0, 2, 1, 3)).reshape(B * T, C, 3)
        clear = template_clearance(at, moved.reshape(B * T, -1, 3), body.template, body.agent_radius)
        clear = clear.reshape(B, T, C).transpose(0, 2, 1)
    return clear, poses


def sequence_clearance(
    pose: np.ndarray,
    actions: np.ndarray,
    obstacles: np.ndarray,
    body: TeamBody,
    obstacle_velocity: np.ndarray | None = None,
    start_step: int = 0,
    mover_uncertainty: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Smallest predicted agent clearance (B, C) and end poses (B, C, 3) of ``step_clearances``."""
    clear, poses = step_clearances(
        pose, actions, obstacles, body, obstacle_velocity, start_step, mover_uncertainty
    )
    return clear.min(axis=-1), poses[:, :, -1]
