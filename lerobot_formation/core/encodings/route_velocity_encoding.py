"""The ``nearest+route+velocity`` obstacle encoding: ``nearest+route`` plus each observed obstacle's velocity.

Why: under moving obstacles the safety layer avoids a mover from its velocity (tracked over many
frames), which the ``nearest+route`` observation does not carry, so a network trained on the layer's
choices cannot tell why it swerved; this encoding gives the network the velocities too.

Layout (float32, 2 + 6 slots + 5 values): the ``nearest`` encoding (goal [x_b, y_b], then per slot
[x_b, y_b, r, present], nearest first), then per slot in the same order the observed velocity
[vx_b, vy_b] [m/s] in the midpoint's body frame (as ``nearest+velocity``: zeros for empty slots and
static obstacles), then the 5 route values of ``nearest+route`` (``core/encodings/route_encoding.py``). The
safety layer decodes the ``nearest`` part, the velocities after the rows and the route after them.
"""

from __future__ import annotations

import numpy as np

from lerobot_formation.core.encodings.encoding import ObstacleEncoding
from lerobot_formation.core.encodings.route_encoding import ROUTE_NAMES, route_features
from lerobot_formation.core.encodings.velocity_encoding import ENCODING as NEAREST_VELOCITY


def _encode(obstacles, mask, goal, pose, slots, map_obstacles=None) -> np.ndarray:
    """``obstacles`` (B, M, 5) [x, y, r, vx, vy]; ``map_obstacles`` (B, M, 3) the map the route plans on."""
    base = NEAREST_VELOCITY.encode(obstacles, mask, goal, pose, slots)
    route = route_features(obstacles[..., :3], mask, goal, pose, slots, map_obstacles)
    return np.concatenate([base, route], axis=1)


def _names(slots: int) -> list[str]:
    return NEAREST_VELOCITY.names(slots) + ROUTE_NAMES


ENCODING = ObstacleEncoding(
    "nearest+route+velocity",
    12,
    4,
    2,
    True,
    _encode,
    _names,
    trailing=5,
    trailing_per_slot=2,
    velocity=True,
    map=True,
)
