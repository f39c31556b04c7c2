"""The ``nearest+velocity`` obstacle encoding: ``nearest`` plus each observed obstacle's velocity.

For moving obstacles (``core.perception.conditions``): a snapshot of positions cannot tell a crossing obstacle
from a static one. Layout (float32): the ``nearest`` encoding (goal [x_b, y_b], then per slot
[x_b, y_b, r, present], nearest first), then per slot, in the same order, the obstacle's observed
velocity [vx_b, vy_b] [m/s] in the midpoint's body frame (x right, y along the heading); empty slots
and static obstacles are zeros: 2 + 6 max_obstacles values. The safety layer decodes the ``nearest``
part as it does for ``nearest``.
"""

from __future__ import annotations

import numpy as np

from lerobot_formation.core.encodings.encoding import (
    ObstacleEncoding,
    encode_nearest,
    nearest_names,
    nearest_order,
)


def body_velocities(velocity: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """World velocities (B, M, 2) in the body frames of poses (B, 3): the rotation of ``world_to_body``."""
    a = pose[:, 2] - np.pi / 2
    c, s = np.cos(a)[:, None], np.sin(a)[:, None]
    vx, vy = velocity[..., 0], velocity[..., 1]
    return np.stack([vx * c + vy * s, -vx * s + vy * c], axis=-1)


def _encode(obstacles, mask, goal, pose, slots) -> np.ndarray:
    B = len(pose)
    base = encode_nearest(obstacles[..., :3], mask, goal, pose, slots)
    order = nearest_order(obstacles[..., :3], mask, pose, slots)
    body = body_velocities(obstacles[..., 3:5], pose)
    present = np.take_along_axis(mask, order, axis=1)[..., None]
    rows = np.zeros((B, slots, 2))
    rows[:, : order.shape[1]] = np.take_along_axis(body, order[..., None], axis=1) * present
    return np.concatenate([base, rows.reshape(B, -1).astype(np.float32)], axis=1)


def _names(slots: int) -> list[str]:
    return nearest_names(slots) + [f"near_{k}_{c}" for k in range(slots) for c in ("vbx", "vby")]


ENCODING = ObstacleEncoding(
    "nearest+velocity", 12, 4, 2, True, _encode, _names, trailing_per_slot=2, velocity=True
)
