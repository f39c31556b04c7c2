"""The planner's obstacle encodings: what ``observation.environment_state`` holds (SPEC "What the
planner sees"). One registry, ``ENCODING_REGISTRY``; a policy config stores the encoding's name.

``grid`` (the paper's, Sec. III): a 7x7 grid of 1 m cells flattened to 49 values, then the goal
[x, y]: 51 values. The obstacle with centre c goes to cell (i, j) = floor(c) - (1, 1) and the cell
stores its radius. With centres in [1.5, 6] the indices are 0..5; centres outside the grid are
dropped (clipped would lie). When two centres share a cell the cell keeps the larger radius: the grid
is a conservative occupancy hint, and the larger obstacle is the one that constrains the path more.

``grid+list``: the grid, the goal, then the exact obstacles [x, y, r], sorted by x then y and
zero-padded to ``max_obstacles`` rows (default 5): 51 + 3 max_obstacles values. A scene with more
obstacles than rows is refused (the list would silently drop some).

``nearest`` (egocentric, any number of obstacles): the goal in the midpoint's body frame (x right,
y along the heading), then the ``max_obstacles`` (default 12) obstacles nearest to the midpoint by
surface distance |c - p| - r, each as [x_b, y_b, r, present] in the body frame, nearest first;
empty slots are zeros (present = 0): 2 + 4 max_obstacles values. A scene with more obstacles runs:
the nearest ones are observed, as a range sensor would. It depends on the midpoint pose, so it is
recomputed every step.

``nearest+route`` (``core/encodings/route_encoding.py``): ``nearest``, then 5 values of PAC's route from the
observed obstacles (the cost-to-go carrots 1 m and 3 m ahead in the body frame, and PAC's path-blocked
flag): 2 + 4 max_obstacles + 5 values.

``nearest+maproute`` (``core/encodings/map_route_encoding.py``): the layout of ``nearest+route``, its route planned
on every obstacle of the team's map instead of the ``max_obstacles`` nearest.
``nearest+velocity`` (``core/encodings/velocity_encoding.py``): ``nearest``, then each slot's observed obstacle
velocity [vx_b, vy_b] in the body frame (moving obstacles, ``core.perception.conditions``): 2 + 6 max_obstacles.

``nearest+route+velocity`` (``core/encodings/route_velocity_encoding.py``): ``nearest+velocity``, then the 5 route
values of ``nearest+route``: 2 + 6 max_obstacles + 5 values.

Every encoding takes the obstacles the team perceives (``core.perception.conditions.Perception``); one with
``velocity`` set gets them as (B, M, 5) rows [x, y, r, vx, vy].

Adding an encoding: one new file that defines ``ENCODING = ObstacleEncoding(...)`` (its ``encode``
and ``names``; ``ObstacleEncoding``, the body frame and the ``nearest`` view are in
``core/encodings/encoding.py``, which the file imports instead of this registry), and one line at the bottom of
this file, ``register("package.module:ENCODING", "name")``: the file is imported when the encoding is
first used.
"""

from __future__ import annotations

import importlib

import numpy as np

from lerobot_formation.core.encodings.encoding import ObstacleEncoding, encode_nearest, nearest_names

GRID_SIZE = 7


def obstacle_grid(obstacles: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Obstacles (B, M, 3) and mask (B, M) -> (B, 49) float32 grid of radii."""
    B, M, _ = obstacles.shape
    idx = np.floor(obstacles[..., :2]).astype(np.int64) - 1  # (B, M, 2)
    inside = mask & (idx >= 0).all(-1) & (idx < GRID_SIZE).all(-1)
    flat = np.where(inside, idx[..., 0] * GRID_SIZE + idx[..., 1], 0)
    grid = np.zeros((B, GRID_SIZE * GRID_SIZE))
    r = np.where(inside, obstacles[..., 2], 0.0)
    np.maximum.at(grid, (np.repeat(np.arange(B), M), flat.ravel()), r.ravel())
    return grid.astype(np.float32)


def _grid_names(_: int) -> list[str]:
    return [f"grid_{i}_{j}" for i in range(GRID_SIZE) for j in range(GRID_SIZE)] + ["goal_x", "goal_y"]


def _encode_grid(obstacles, mask, goal, pose, max_obstacles) -> np.ndarray:
    return np.concatenate([obstacle_grid(obstacles, mask), goal.astype(np.float32)], axis=1)


def _grid_list_names(max_obstacles: int) -> list[str]:
    return _grid_names(0) + [f"obstacle_{k}_{c}" for k in range(max_obstacles) for c in ("x", "y", "r")]


def _encode_grid_list(obstacles, mask, goal, pose, max_obstacles) -> np.ndarray:
    B, M, _ = obstacles.shape
    count = mask.sum(axis=1)
    if int(count.max(initial=0)) > max_obstacles:
        b = int(np.argmax(count))
        raise ValueError(
            f"scene {b} has {int(count[b])} obstacles, more than the {max_obstacles} rows of the "
            f"'grid+list' encoding (max_obstacles={max_obstacles}); use the 'nearest' encoding for "
            "scenes with more obstacles"
        )
    key = np.where(mask, obstacles[..., 0] * 1e3 + obstacles[..., 1], np.inf)
    order = np.argsort(key, axis=1, kind="stable")
    sorted_obs = np.take_along_axis(np.where(mask[..., None], obstacles, 0.0), order[..., None], axis=1)
    lst = np.zeros((B, max_obstacles, 3))
    m = min(M, max_obstacles)
    lst[:, :m] = sorted_obs[:, :m]
    return np.concatenate(
        [_encode_grid(obstacles, mask, goal, pose, 0), lst.reshape(B, -1).astype(np.float32)], axis=1
    )


# Encodings by name: an ObstacleEncoding, or the "module:attribute" path of one (imported when first used).
ENCODING_REGISTRY: dict[str, ObstacleEncoding | str] = {}


def register(encoding: ObstacleEncoding | str, name: str | None = None) -> None:
    """Register an encoding under its name, or the ``"module:attribute"`` path of one under ``name``."""
    if isinstance(encoding, str):
        if not name:
            raise ValueError(f"register({encoding!r}) needs the encoding's name")
        ENCODING_REGISTRY[name] = encoding
    else:
        ENCODING_REGISTRY[encoding.name] = encoding


def get_encoding(name: str) -> ObstacleEncoding:
    if name not in ENCODING_REGISTRY:
        raise ValueError(f"obstacle encoding must be one of {tuple(ENCODING_REGISTRY)}, got {name!r}")
    encoding = ENCODING_REGISTRY[name]
    if isinstance(encoding, str):  # "module:attribute": import it now, once
        module, _, attr = encoding.partition(":")
        encoding = getattr(importlib.import_module(module), attr)
        if encoding.name != name:
            raise ValueError(
                f"{ENCODING_REGISTRY[name]} is the encoding {encoding.name!r}, registered as {name!r}"
            )
        ENCODING_REGISTRY[name] = encoding
    return encoding


def environment_state_dim(encoding: str = "grid", max_obstacles: int | None = None) -> int:
    return get_encoding(encoding).dim(max_obstacles)


def environment_state(
    obstacles: np.ndarray,
    mask: np.ndarray,
    goal: np.ndarray,
    encoding: str = "grid",
    max_obstacles: int | None = None,
    pose: np.ndarray | None = None,
    obstacle_velocity: np.ndarray | None = None,
    map_obstacles: np.ndarray | None = None,
) -> np.ndarray:
    """The ``environment_state`` observation (B, D) float32 of ``encoding`` (see the module docstring);
    ``obstacle_velocity`` (B, M, 2) the observed velocities (None: static obstacles); ``map_obstacles``
    (B, M, 3) the map a route-planning encoding plans on (None: ``obstacles``)."""
    enc = get_encoding(encoding)
    if enc.map and map_obstacles is None:
        map_obstacles = obstacles[..., :3]
    if enc.velocity:
        vel = np.zeros((*obstacles.shape[:2], 2)) if obstacle_velocity is None else obstacle_velocity
        obstacles = np.concatenate([obstacles[..., :3], vel], axis=-1)
    if enc.map:
        return enc.encode(obstacles, mask, goal, pose, enc.slots(max_obstacles), map_obstacles=map_obstacles)
    return enc.encode(obstacles, mask, goal, pose, enc.slots(max_obstacles))


register(ObstacleEncoding("grid", 0, 0, GRID_SIZE * GRID_SIZE + 2, False, _encode_grid, _grid_names))
register(
    ObstacleEncoding("grid+list", 5, 3, GRID_SIZE * GRID_SIZE + 2, False, _encode_grid_list, _grid_list_names)
)
register(ObstacleEncoding("nearest", 12, 4, 2, True, encode_nearest, nearest_names))
# An encoding in its own file: register("package.module:ENCODING", "its-name") here.
register("lerobot_formation.core.encodings.route_encoding:ENCODING", "nearest+route")
register("lerobot_formation.core.encodings.map_route_encoding:ENCODING", "nearest+maproute")
register("lerobot_formation.core.encodings.velocity_encoding:ENCODING", "nearest+velocity")
register("lerobot_formation.core.encodings.route_velocity_encoding:ENCODING", "nearest+route+velocity")
register("lerobot_formation.core.encodings.mover_route_encoding:ENCODING", "nearest+moverroute+velocity")
ENCODINGS = tuple(ENCODING_REGISTRY)


def egocentric_encodings() -> tuple[str, ...]:
    """Names of the encodings the safety layer can decode obstacles from (a list in the midpoint's
    frame). A function, not a constant: it resolves every lazily registered encoding's module."""
    return tuple(name for name in ENCODINGS if get_encoding(name).egocentric)


def route_encodings() -> tuple[str, ...]:
    """Names of the encodings that carry the route hint (``core.encodings.route_encoding``), which route pursuit
    and the safety layer's route proposal read."""
    return tuple(name for name in ENCODINGS if get_encoding(name).map)
