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


def route_velocity_encoding(name: str, movers_on_map: bool = False) -> ObstacleEncoding:
    """The ``nearest+velocity`` rows and velocities, then the 5 route values, planned on the team's map,
    or with ``movers_on_map`` on that map with every observed mover where it is now (an observed
    velocity that is not zero; ``nearest+moverroute+velocity``, ``core/encodings/mover_route_encoding.py``)."""

    def encode(obstacles, mask, goal, pose, slots, map_obstacles=None) -> np.ndarray:
        """``obstacles`` (B, M, 5) [x, y, r, vx, vy]; ``map_obstacles`` (B, M, 3) the team's map."""
        base = NEAREST_VELOCITY.encode(obstacles, mask, goal, pose, slots)
        observed = obstacles[..., :3]
        if movers_on_map:  # as RoutePursuitController.act
            moving = np.any(obstacles[..., 3:5] != 0, axis=-1)
            source = observed if map_obstacles is None else map_obstacles
            map_obstacles = np.where(moving[..., None], observed, source)
        route = route_features(observed, mask, goal, pose, slots, map_obstacles)
        return np.concatenate([base, route], axis=1)

    return ObstacleEncoding(
        name,
        12,
        4,
        2,
        True,
        encode,
        lambda slots: NEAREST_VELOCITY.names(slots) + ROUTE_NAMES,
        trailing=5,
        trailing_per_slot=2,
        velocity=True,
        map=True,
    )


ENCODING = route_velocity_encoding("nearest+route+velocity")
