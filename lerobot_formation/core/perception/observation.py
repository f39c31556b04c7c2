"""What the planner observes of B teams: the one observation builder of the env, the vector env, the
engine's diffusion controller and the dataset writer (which must all give the policy the same bits).

- ``agent_pos`` (LeRobot's ``observation.state``), (B, 7) float32: the midpoint
  [x, y, cos phi, sin phi, x', y', omega], the velocity being the one applied over the last control
  step (zero at the start), as ``dynamics.step`` stores it in ``FormationState.velocity``.
- ``environment_state`` (``observation.environment_state``), (B, D) float32: the obstacle encoding of
  ``core/encodings/obstacle_grid.py``. A world-frame encoding (grid, grid+list) does not change during an
  episode, so a caller may pass the one it computed at the episode's start; an egocentric one
  ("nearest") moves with the team and is computed at every pose.
"""

from __future__ import annotations

import numpy as np

from lerobot_formation.core.encodings.obstacle_grid import environment_state, get_encoding
from lerobot_formation.core.world.dynamics import midpoint_velocity

STATE_DIM = 7
STATE_NAMES = ["x", "y", "cos_phi", "sin_phi", "x_dot", "y_dot", "omega"]


def midpoint_state(pose: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """``agent_pos`` (B, 7) float32 of poses (B, 3) and velocities (B, 3): [x, y, cos phi, sin phi,
    x', y', omega]."""
    return np.concatenate([pose[:, :2], np.cos(pose[:, 2:3]), np.sin(pose[:, 2:3]), velocity], axis=1).astype(
        np.float32
    )


def observed_velocities(poses: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """The velocities (n, 3) observed along one episode of poses (n, 3) before actions (n, 2): frame t
    sees the (clipped) action of step t - 1 applied at heading phi_{t-1}, frame 0 sees zeros."""
    velocity = np.zeros((len(poses), 3))
    velocity[1:] = midpoint_velocity(poses[:-1], actions[:-1])
    return velocity


def observe(
    pose: np.ndarray,
    velocity: np.ndarray,
    obstacles: np.ndarray,
    mask: np.ndarray,
    goal: np.ndarray,
    encoding: str = "grid",
    max_obstacles: int | None = None,
    world_state: np.ndarray | None = None,
    obstacle_velocity: np.ndarray | None = None,
    map_obstacles: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """``{"agent_pos": (B, 7), "environment_state": (B, D)}`` of B teams at ``pose`` (B, 3).

    The scene arrays (obstacles (S, M, 3), mask (S, M), goal (S, 2)) hold S = B scenes, one per team,
    or S = 1 scene for every row (the frames of one episode). ``world_state`` (B, D) is a world-frame
    encoding computed before for these scenes (the episode's start): returned as it is, not
    recomputed; an egocentric encoding ignores it. ``obstacle_velocity`` (S, M, 2): the observed
    obstacle velocities, for an encoding that observes them (None: static). ``map_obstacles`` (S, M, 3):
    the map snapshot the route hint plans on (``core.perception.conditions.Perception.map_obstacles``; None:
    ``obstacles``, as without conditions).
    """
    B = len(pose)
    if get_encoding(encoding).egocentric:  # moves with the team: one encoding per pose
        if len(goal) != B:
            obstacles, mask, goal = (np.repeat(a, B, axis=0) for a in (obstacles, mask, goal))
            if obstacle_velocity is not None:
                obstacle_velocity = np.repeat(obstacle_velocity, B, axis=0)
            if map_obstacles is not None:
                map_obstacles = np.repeat(map_obstacles, B, axis=0)
        env = environment_state(
            obstacles,
            mask,
            goal,
            encoding,
            max_obstacles,
            pose=pose,
            obstacle_velocity=obstacle_velocity,
            map_obstacles=map_obstacles,
        )
    else:
        env = (
            world_state
            if world_state is not None
            else environment_state(
                obstacles,
                mask,
                goal,
                encoding,
                max_obstacles,
                obstacle_velocity=obstacle_velocity,
                map_obstacles=map_obstacles,
            )
        )
        if len(env) != B:
            env = np.repeat(env, B, axis=0)
    return {"agent_pos": midpoint_state(pose, velocity), "environment_state": env}


def observe_perception(
    view, encoding: str = "grid", max_obstacles: int | None = None
) -> dict[str, np.ndarray]:
    """``observe`` of what B teams perceive: ``view`` is a ``core.perception.conditions.Perception`` (its pose,
    velocity, observed obstacles, their mask and velocities, the goal and the map snapshot the route
    hint plans on). The one mapping from a perception to an observation: the rollout's teams and the
    engine's diffusion controller both call it."""
    return observe(
        view.pose,
        view.velocity,
        view.obstacles,
        view.mask,
        view.goal,
        encoding,
        max_obstacles,
        obstacle_velocity=view.obstacle_velocity,
        map_obstacles=view.map_obstacles,
    )
