"""The ``nearest+route`` obstacle encoding: ``nearest`` plus a route hint computed from what it observes.

Why: PAC (``core/controllers/pac.py``) picks its detour side from a grid cost-to-go over the whole obstacle layout
(``core/world/navigation.py``), a global decision that a small denoiser conditioned on the 12 nearest obstacles
must otherwise re-derive from scratch every replan; when it re-derives it differently on consecutive
replans the team swings between sides and hits the obstacle in between. This encoding gives it the
same route the expert follows, computed only from the observation's own content (the goal and the
``max_obstacles`` nearest obstacles), so nothing privileged enters and the safety layer still decodes
the ``nearest`` part.

Layout (2 + 4 slots + 5 values, float32): the ``nearest`` encoding (goal [x_b, y_b], then per slot
[x_b, y_b, r, present]), then

- ``route_near_bx, route_near_by``: the cost-to-go carrot ``NEAR_CELLS`` cells (1 m) down the steepest
  descent from the midpoint, in the body frame (PAC's detour target, Sec. V-A path check);
- ``route_far_bx, route_far_by``: the carrot ``FAR_CELLS`` cells (3 m) on, for anticipation;
- ``path_blocked``: 1 when PAC's path check finds the straight segment to the goal blocked (then PAC
  steers for the near carrot instead of the goal), else 0.

The cost-to-go (obstacles inflated by PAC's ``path_inflate``) is built on the team's map
(``core.perception.conditions.Perception.map_obstacles``: the observed static obstacles as observed when the map
last changed, the same map PAC plans on), from its ``max_obstacles`` obstacles nearest the midpoint.
It depends only on that map, not on the pose (unless the nearest selection changes), so it is
computed once per distinct map (``navigation.SceneFields``, cached, the same field PAC uses) and each
step costs a few array look-ups; under obstacle noise or moving obstacles the map, and so the field,
stays the same between map changes. The path check reads the current observed obstacles (noisy,
moving ones included), as PAC's does. Without conditions the map is the observed obstacles.
"""

from __future__ import annotations

import numpy as np

from lerobot_formation.core.encodings.encoding import (
    ObstacleEncoding,
    encode_nearest,
    nearest_names,
    nearest_order,
    world_to_body,
)
from lerobot_formation.core.world import navigation

NEAR_CELLS = navigation.PAC_CARROT_CELLS  # 5 cells of 0.2 m: PAC's carrot
FAR_CELLS = 15
ROUTE_NAMES = ["route_near_bx", "route_near_by", "route_far_bx", "route_far_by", "path_blocked"]


def observed_obstacles(obstacles: np.ndarray, mask: np.ndarray, pose: np.ndarray, slots: int) -> np.ndarray:
    """The world-frame obstacles (B, slots, 3) that the ``nearest`` part observes; empty slots zero."""
    order = nearest_order(obstacles, mask, pose, slots)
    seen = np.take_along_axis(np.where(mask[..., None], obstacles, 0.0), order[..., None], axis=1)
    seen *= np.take_along_axis(mask, order, axis=1)[..., None]
    out = np.zeros((len(pose), slots, 3))
    out[:, : seen.shape[1]] = seen
    return out


def route_features(
    obstacles, mask, goal, pose, slots: int, map_obstacles=None, whole_map: bool = False
) -> np.ndarray:
    """The 5 route values (B, 5) float32 of B midpoints (see the module docstring): the carrots on the
    cost-to-go of ``map_obstacles`` (B, M, 3) (None: ``obstacles``), the path check on ``obstacles``.
    The cost-to-go sees the ``slots`` map obstacles nearest the midpoint, or with ``whole_map`` every
    one of them (``nearest+maproute``, ``core/encodings/map_route_encoding.py``)."""
    B = len(pose)
    observed = observed_obstacles(obstacles, mask, pose, slots)
    source = obstacles if map_obstacles is None else map_obstacles
    planned = source.shape[1] if whole_map else slots
    mapped = (
        observed
        if map_obstacles is None and not whole_map
        else observed_obstacles(source, mask, pose, planned)
    )
    goal = np.asarray(goal, np.float64)
    fields = navigation.SceneFields.build(
        mapped, goal, inflate=navigation.PAC_PATH_INFLATE
    )  # PAC's field of the same map
    near = fields.carrot(pose[:, :2], NEAR_CELLS)
    far = fields.carrot(near, FAR_CELLS - NEAR_CELLS)
    blocked = navigation.path_blocked(
        pose[:, :2], goal, observed, navigation.PAC_LOOKAHEAD, navigation.PAC_INFLATE
    )
    body = world_to_body(np.stack([near, far], axis=1), pose)  # (B, 2, 2)
    return np.concatenate([body.reshape(B, 4), blocked[:, None]], axis=1).astype(np.float32)


def route_encoding(name: str, whole_map: bool = False) -> ObstacleEncoding:
    """The ``nearest`` rows, then the 5 route values (``route_features``, ``whole_map`` passed on):
    ``nearest+route`` here, ``nearest+maproute`` (``core/encodings/map_route_encoding.py``) on the whole map."""

    def encode(obstacles, mask, goal, pose, slots, map_obstacles=None) -> np.ndarray:
        base = encode_nearest(obstacles, mask, goal, pose, slots)
        route = route_features(obstacles, mask, goal, pose, slots, map_obstacles, whole_map)
        return np.concatenate([base, route], axis=1)

    return ObstacleEncoding(
        name, 12, 4, 2, True, encode, lambda slots: nearest_names(slots) + ROUTE_NAMES, trailing=5, map=True
    )


ENCODING = route_encoding("nearest+route")
