"""The planner's obstacle encoding (paper Sec. III, SPEC "What the planner sees").

7x7 grid of 1 m cells flattened to 49 values. The obstacle with centre c goes to cell
(i, j) = floor(c) - (1, 1) and the cell stores its radius. With centres in [1.5, 6] the indices
are 0..5; centres outside the grid are dropped (clipped would lie). When two centres share a cell the
cell keeps the larger radius: the grid is a conservative occupancy hint, and the larger obstacle is
the one that constrains the path more.

``environment_state`` appends the goal (2 values) to the grid: 51 values, the paper's encoding
("grid"). The "grid+list" encoding also appends the exact obstacles [x, y, r], sorted by x then y
and zero-padded to ``max_obstacles`` rows: 51 + 3 * max_obstacles values. The grid alone cannot say
where in its 1 m cell an obstacle sits; the list can.
"""

from __future__ import annotations

import numpy as np

GRID_SIZE = 7
ENCODINGS = ("grid", "grid+list")


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


def environment_state_dim(encoding: str = "grid", max_obstacles: int = 5) -> int:
    if encoding not in ENCODINGS:
        raise ValueError(f"obstacle encoding must be one of {ENCODINGS}, got {encoding!r}")
    return GRID_SIZE * GRID_SIZE + 2 + (3 * max_obstacles if encoding == "grid+list" else 0)


def environment_state(
    obstacles: np.ndarray, mask: np.ndarray, goal: np.ndarray, encoding: str = "grid", max_obstacles: int = 5
) -> np.ndarray:
    """The ``environment_state`` observation, (B, 51) for "grid" or (B, 51 + 3 max_obstacles) float32."""
    environment_state_dim(encoding, max_obstacles)
    parts = [obstacle_grid(obstacles, mask), goal.astype(np.float32)]
    if encoding == "grid+list":
        B, M, _ = obstacles.shape
        if int(mask.sum(axis=1).max(initial=0)) > max_obstacles:
            raise ValueError(
                f"a scene has {int(mask.sum(axis=1).max())} obstacles, more than {max_obstacles=}"
            )
        key = np.where(mask, obstacles[..., 0] * 1e3 + obstacles[..., 1], np.inf)
        order = np.argsort(key, axis=1, kind="stable")
        sorted_obs = np.take_along_axis(np.where(mask[..., None], obstacles, 0.0), order[..., None], axis=1)
        lst = np.zeros((B, max_obstacles, 3))
        m = min(M, max_obstacles)
        lst[:, :m] = sorted_obs[:, :m]
        parts.append(lst.reshape(B, -1).astype(np.float32))
    return np.concatenate(parts, axis=1)
