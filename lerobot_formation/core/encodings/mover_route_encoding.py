"""The ``nearest+moverroute+velocity`` obstacle encoding: ``nearest+route+velocity`` whose route hint
plans around the observed moving obstacles where they are now.

Why: ``nearest+route+velocity``'s hint plans on the team's map, which leaves the movers out, so a
network that corrects route pursuit's chunk (``action_space: route-residual``) must add the whole
avoidance of the movers. Route pursuit itself (``core/controllers/route_pursuit.py``) rebuilds its
cost-to-go with each observed mover where it is now; this hint is that same route, so the residual's
prior is route pursuit's own chunk (the first command equal to route pursuit's).

Layout: that of ``nearest+route+velocity`` (``core/encodings/route_velocity_encoding.py``); only the 5
route values differ, and only while a mover is observed (an observed velocity that is not zero):
the cost-to-go is then built on the map with every observed mover in place of its map entry, at every
step (no cache hit, as route pursuit's).
"""

from __future__ import annotations

import numpy as np

from lerobot_formation.core.encodings.encoding import ObstacleEncoding
from lerobot_formation.core.encodings.route_encoding import ROUTE_NAMES, route_features
from lerobot_formation.core.encodings.velocity_encoding import ENCODING as NEAREST_VELOCITY


def _encode(obstacles, mask, goal, pose, slots, map_obstacles=None) -> np.ndarray:
    """``obstacles`` (B, M, 5) [x, y, r, vx, vy]; ``map_obstacles`` (B, M, 3) the team's map."""
    base = NEAREST_VELOCITY.encode(obstacles, mask, goal, pose, slots)
    observed = obstacles[..., :3]
    moving = np.any(obstacles[..., 3:5] != 0, axis=-1)
    source = observed if map_obstacles is None else map_obstacles
    plan = np.where(moving[..., None], observed, source)  # as RoutePursuitController.act
    route = route_features(observed, mask, goal, pose, slots, plan)
    return np.concatenate([base, route], axis=1)


def _names(slots: int) -> list[str]:
    return NEAREST_VELOCITY.names(slots) + ROUTE_NAMES


ENCODING = ObstacleEncoding(
    "nearest+moverroute+velocity",
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
