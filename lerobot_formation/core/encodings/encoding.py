"""What every obstacle encoding builds on: the ``ObstacleEncoding`` type, the body frame, and the
egocentric ``nearest`` view (goal and the nearest obstacles in the midpoint's frame).

The registry of encodings by name is ``core/encodings/obstacle_grid.py``; an encoding in its own file (e.g.
``core/encodings/route_encoding.py``) imports this module, never the registry, so the registry may name it by
its "module:attribute" path without an import cycle.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

BODY_POSE = np.array([0.0, 0.0, np.pi / 2])  # the midpoint in its own body frame, facing +y


def world_to_body(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """World points (B, ..., 2) into the body frames of poses (B, 3): x right, y along the heading.

    The inverse of ``dynamics.rotate_body`` plus the translation: body = R(phi - pi/2)^T (p - p_m).
    """
    B = len(pose)
    shape = (B,) + (1,) * (points.ndim - 2)
    a = pose[:, 2] - np.pi / 2
    c, s = np.cos(a).reshape(shape), np.sin(a).reshape(shape)
    dx = points[..., 0] - pose[:, 0].reshape(shape)
    dy = points[..., 1] - pose[:, 1].reshape(shape)
    return np.stack([dx * c + dy * s, -dx * s + dy * c], axis=-1)


def nearest_names(max_obstacles: int) -> list[str]:
    return ["goal_bx", "goal_by"] + [
        f"near_{k}_{c}" for k in range(max_obstacles) for c in ("bx", "by", "r", "present")
    ]


def nearest_order(obstacles: np.ndarray, mask: np.ndarray, pose: np.ndarray, slots: int) -> np.ndarray:
    """Indices (B, min(M, slots)) of the obstacles (B, M, 3) nearest to the midpoints (B, 3) by surface
    distance, nearest first; masked-out slots sort last."""
    centres = world_to_body(obstacles[..., :2], pose)  # the body frame: the same bits as the encoding's
    surface = np.where(mask, np.linalg.norm(centres, axis=-1) - obstacles[..., 2], np.inf)
    return np.argsort(surface, axis=1, kind="stable")[:, :slots]


def encode_nearest(obstacles, mask, goal, pose, max_obstacles) -> np.ndarray:
    if pose is None:
        raise ValueError("the 'nearest' encoding is egocentric: environment_state needs the midpoint pose")
    B, M, _ = obstacles.shape
    goal_b = world_to_body(goal[:, None, :], pose)[:, 0]  # (B, 2)
    centres = world_to_body(obstacles[..., :2], pose)  # (B, M, 2)
    order = nearest_order(obstacles, mask, pose, max_obstacles)
    m = order.shape[1]
    rows = np.zeros((B, max_obstacles, 4))
    take = lambda a: np.take_along_axis(a, order, axis=1)  # noqa: E731
    present = take(mask)
    rows[:, :m, 0] = take(centres[..., 0])
    rows[:, :m, 1] = take(centres[..., 1])
    rows[:, :m, 2] = take(obstacles[..., 2])
    rows[:, :m, 3] = 1.0
    rows[:, :m] *= present[..., None]
    return np.concatenate([goal_b, rows.reshape(B, -1)], axis=1).astype(np.float32)


@dataclass(frozen=True)
class ObstacleEncoding:
    """One way to write obstacles and goal into ``observation.environment_state``.

    Attributes:
        name: registry key, stored in env and policy configs.
        default_slots: obstacle rows when ``max_obstacles`` is not given (0: no rows).
        per_slot: values per obstacle row.
        fixed: values before the rows (grid and goal).
        egocentric: depends on the midpoint pose, so the env recomputes it every step.
        encode: (obstacles (B, M, 3), mask (B, M), goal (B, 2), pose (B, 3) | None, slots) -> (B, D).
        names: slots -> the D feature names.
        trailing: values after the rows (e.g. a route hint); a row layout that starts like
            "nearest"'s (``fixed`` 2, ``per_slot`` 4) is what the safety layer decodes.
        trailing_per_slot: values per obstacle slot after ``trailing`` (e.g. the slots' velocities).
        velocity: ``encode`` takes obstacles (B, M, 5) [x, y, r, vx, vy] (observed velocities).
        map: ``encode`` takes ``map_obstacles`` (B, M, 3), the map snapshot it plans a route on
            (``core.perception.conditions.Perception.map_obstacles``), as a keyword.
    """

    name: str
    default_slots: int
    per_slot: int
    fixed: int
    egocentric: bool
    encode: Callable[..., np.ndarray]
    names: Callable[[int], list[str]]
    trailing: int = 0
    trailing_per_slot: int = 0
    velocity: bool = False
    map: bool = False

    def slots(self, max_obstacles: int | None) -> int:
        return self.default_slots if max_obstacles is None or not self.per_slot else int(max_obstacles)

    def dim(self, max_obstacles: int | None = None) -> int:
        slots = self.slots(max_obstacles)
        return self.fixed + (self.per_slot + self.trailing_per_slot) * slots + self.trailing

    def route_hint(
        self, env_state: np.ndarray, max_obstacles: int | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(route (..., 4), goal (..., 2)) of an encoding with a route hint (``map``), in the body frame
        of the midpoint: the near and far carrots (after the rows and their per-slot values) and the goal
        (the last two values before the rows), as route pursuit reads them (``pursuit_chunk``)."""
        if not self.map:
            raise ValueError(f"the {self.name!r} encoding carries no route hint")
        env_state = np.asarray(env_state, dtype=np.float64)
        if env_state.shape[-1] != self.dim(max_obstacles):
            raise ValueError(
                f"the {self.name!r} encoding with max_obstacles={max_obstacles} has {self.dim(max_obstacles)} "
                f"values, got shape {env_state.shape}"
            )
        at = self.fixed + (self.per_slot + self.trailing_per_slot) * self.slots(max_obstacles)
        return env_state[..., at : at + 4], env_state[..., self.fixed - 2 : self.fixed]
