"""Which scenes are possible: the checks of given scenes (``check_scenes``: a scenes file's, a scene
set's) and the validity check of sampled candidates (``scene_validity``, ``validity_first``), run on
all candidates of all seeds at once:

1. no obstacle covers the start formation (each start agent keeps ``start_margin`` of clearance,
   and the midpoint keeps the formation half-width);
2. no obstacle sits within the formation's radius (1.12 m for the square) of the goal;
3. a passage exists: a flood fill on a 0.1 m grid, with obstacles inflated by the formation's
   half-width plus the agent radius, connects the start midpoint to the goal.
"""

from __future__ import annotations

import numpy as np

from lerobot_formation.core.world.dynamics import rotate_body
from lerobot_formation.core.world.geometry import obstacle_gaps
from lerobot_formation.core.world.navigation import grid_cell, grid_size, inflated_cells, neighbour_slices
from lerobot_formation.core.world.presets import SceneConfig
from lerobot_formation.core.world.scenes import MAX_COORDINATE, MAX_GOAL_DISTANCE, MAX_OBSTACLE_VALUE, Scenes


def check_scenes(scenes: Scenes, config: SceneConfig | None = None) -> None:
    """Raise ValueError naming the first impossible scene: NaN, negative radius, start or goal out of
    range (``MAX_COORDINATE``, ``MAX_GOAL_DISTANCE``), obstacle over the start formation, a goal
    inside an obstacle, or no passage from the start to the goal (``passage_exists``)."""
    config = config or SceneConfig()
    for name in ("obstacles", "goal", "start"):
        arr = getattr(scenes, name)
        bad = ~np.isfinite(arr)
        if bad.any():
            b = int(np.argwhere(bad)[0][0])
            raise ValueError(f"scene {b}: {name} contains a non-finite value: {arr[b].tolist()}")
    r = scenes.obstacles[..., 2]
    neg = (r <= 0) & scenes.mask
    if neg.any():
        b, m = np.argwhere(neg)[0]
        raise ValueError(f"scene {b}: obstacle {m} has a non-positive radius {r[b, m]}")
    huge = (np.abs(scenes.obstacles) > MAX_OBSTACLE_VALUE).any(axis=-1) & scenes.mask
    if huge.any():
        b, m = np.argwhere(huge)[0]
        raise ValueError(
            f"scene {b}: obstacle {m} {scenes.obstacles[b, m].tolist()} has a value beyond "
            f"{MAX_OBSTACLE_VALUE:g} m (x, y and r must lie within [-{MAX_OBSTACLE_VALUE:g}, {MAX_OBSTACLE_VALUE:g}])"
        )
    dist = np.linalg.norm(scenes.goal - scenes.start[:, :2], axis=1)
    if (dist > MAX_GOAL_DISTANCE).any():
        b = int(np.flatnonzero(dist > MAX_GOAL_DISTANCE)[0])
        raise ValueError(
            f"scene {b}: goal {scenes.goal[b].tolist()} is {dist[b]:.1f} m from the start "
            f"{scenes.start[b, :2].tolist()}; at most {MAX_GOAL_DISTANCE:g} m is supported (a team covers "
            "at most v_max * max_steps * dt = 36 m in an episode)"
        )
    for name, arr in (("start", scenes.start[:, :2]), ("goal", scenes.goal)):
        out = (np.abs(arr) > MAX_COORDINATE).any(axis=1)
        if out.any():
            b = int(np.flatnonzero(out)[0])
            raise ValueError(
                f"scene {b}: {name} {arr[b].tolist()} lies outside the supported workspace "
                f"[-{MAX_COORDINATE:g}, {MAX_COORDINATE:g}] m x [-{MAX_COORDINATE:g}, {MAX_COORDINATE:g}] m"
            )
    from lerobot_formation.core.world.formation_graph import FormationGraph

    tmpl = np.asarray(FormationGraph().template)
    start_agents = _start_agents(scenes.start, tmpl)  # (B, N, 2)
    gap = obstacle_gaps(start_agents, scenes.obstacles) - config.agent_radius  # (B, N, M)
    hit = (gap < 0) & scenes.mask[:, None, :]
    if hit.any():
        b, n, m = np.argwhere(hit)[0]
        raise ValueError(
            f"scene {b}: obstacle {m} {scenes.obstacles[b, m].tolist()} lies over the start formation "
            f"(agent {n} at {start_agents[b, n].round(3).tolist()})"
        )
    g = obstacle_gaps(scenes.goal[:, None, :], scenes.obstacles)[:, 0]  # (B, M)
    inside = (g < 0) & scenes.mask
    if inside.any():
        b, m = np.argwhere(inside)[0]
        raise ValueError(
            f"scene {b}: goal {scenes.goal[b].tolist()} lies inside obstacle {m} {scenes.obstacles[b, m].tolist()}"
        )
    walled = ~passage_exists(scenes, config)
    if walled.any():
        b = int(np.flatnonzero(walled)[0])
        inflate = config.half_width + config.agent_radius
        raise ValueError(
            f"scene {b}: no passage from the start {scenes.start[b, :2].tolist()} to the goal "
            f"{scenes.goal[b].tolist()}: the obstacles, inflated by the formation's half-width plus the "
            f"agent radius ({inflate:g} m), wall the goal off (or cover the start or the goal)"
        )


def _start_agents(start: np.ndarray, template: np.ndarray) -> np.ndarray:
    """Template agent positions at the start pose, (B, N, 2). Body frame: y along the heading."""
    return rotate_body(template[None], start[:, 2][:, None]) + start[:, None, :2]


def _cheap_reason(cand: Scenes, config: SceneConfig) -> np.ndarray:
    """Reason codes of the geometric checks: 0 ok, 1 start formation covered, 2 obstacle near goal."""
    from lerobot_formation.core.world.formation_graph import FormationGraph

    tmpl = np.asarray(FormationGraph().template)
    agents = _start_agents(cand.start, tmpl)
    start_gap = obstacle_gaps(agents, cand.obstacles) - config.agent_radius - config.start_margin
    mid_gap = (
        obstacle_gaps(cand.start[:, None, :2], cand.obstacles)[:, 0] - config.half_width - config.agent_radius
    )
    covered = ((start_gap < 0).any(axis=(1, 2))) | ((mid_gap < 0).any(axis=1))
    goal_gap = obstacle_gaps(cand.goal[:, None, :], cand.obstacles)[:, 0] - config.formation_radius
    near_goal = (goal_gap < 0).any(axis=1)
    reason = np.zeros(len(cand), dtype=np.int64)
    reason[near_goal] = 2
    reason[covered] = 1
    return reason


def scene_validity(scenes: Scenes, config: SceneConfig) -> tuple[np.ndarray, np.ndarray]:
    """Validity of a batch of candidate scenes.

    Returns:
        valid: (B,) bool.
        reason: (B,) int, 0 valid, 1 start covered, 2 obstacle too close to the goal, 3 no passage.
    """
    reason = _cheap_reason(scenes, config)
    idx = np.flatnonzero(reason == 0)
    if len(idx):
        ok = passage_exists(scenes[idx], config)
        reason[idx[~ok]] = 3
    return reason == 0, reason


def passage_exists(scenes: Scenes, config: SceneConfig) -> np.ndarray:
    """Flood fill from the start midpoint to the goal on a grid, obstacles inflated by the formation
    half-width plus the agent radius. (B,) bool. Runs on all scenes at once."""
    res = config.grid_resolution
    lo = min(-2.5, float(np.min(scenes.start[:, :2])) - 2.5, float(np.min(scenes.goal)) - 2.5)
    hi = max(8.5, float(np.max(scenes.start[:, :2])) + 2.5, float(np.max(scenes.goal)) + 2.5)
    n = grid_size(lo, hi, res)
    chunk = max(1, _PASSAGE_CELLS // (n * n))  # bounded memory; the same grid for every chunk
    if len(scenes) > chunk:
        return np.concatenate(
            [_flood_fill(scenes[i : i + chunk], config, lo, n) for i in range(0, len(scenes), chunk)]
        )
    return _flood_fill(scenes, config, lo, n)


_PASSAGE_CELLS = 1 << 24  # grid cells of one flood fill batch (a few 16 MB boolean arrays)


def _flood_fill(scenes: Scenes, config: SceneConfig, lo: float, n: int) -> np.ndarray:
    res = config.grid_resolution
    inflate = config.half_width + config.agent_radius
    free = ~inflated_cells(scenes.obstacles, scenes.mask, inflate, lo, res, n)  # (B, n, n)
    B = len(scenes)
    si = grid_cell(scenes.start[:, :2], lo, res, n)
    gi = grid_cell(scenes.goal, lo, res, n)
    reach = np.zeros_like(free)
    reach[np.arange(B), si[:, 0], si[:, 1]] = True
    reach &= free
    goal_free = free[np.arange(B), gi[:, 0], gi[:, 1]]
    shifts = [neighbour_slices(dx, dy, n) for dx, dy in ((-1, 0), (1, 0), (0, -1), (0, 1))]  # 4-connected
    for it in range(4 * n):
        grown = reach.copy()
        for src, dst in shifts:
            grown[dst] |= reach[src]
        grown &= free
        if it % 8 == 0:
            done = reach[np.arange(B), gi[:, 0], gi[:, 1]] | ~goal_free
            if done.all() or np.array_equal(grown, reach):
                reach = grown
                break
        reach = grown
    return reach[np.arange(B), gi[:, 0], gi[:, 1]] & goal_free


def validity_first(cand: Scenes, config: SceneConfig, P: int, C: int) -> tuple[np.ndarray, np.ndarray]:
    """Validity of candidates, running the (costly) passage check only up to the first candidate of
    each seed that passes it. Unchecked later candidates are reported invalid with reason 0 and are
    never used, because sampling takes the first valid one."""
    reason = _cheap_reason(cand, config)
    valid = np.zeros(P * C, dtype=bool)
    cheap_ok = (reason == 0).reshape(P, C)
    unresolved = np.ones(P, dtype=bool)
    for _ in range(C):
        # first still-unchecked cheap-valid candidate of each unresolved seed
        has = cheap_ok.any(axis=1) & unresolved
        if not has.any():
            break
        first = np.argmax(cheap_ok, axis=1)
        rows = np.flatnonzero(has)
        idx = rows * C + first[rows]
        ok = passage_exists(cand[idx], config)
        valid[idx[ok]] = True
        reason[idx[~ok]] = 3
        cheap_ok[rows, first[rows]] = False
        unresolved[rows[ok]] = False
        # candidates after a valid one are never used: stop checking them
    # later cheap-valid candidates of resolved seeds stay "valid=False, reason=0"; only the first is used
    return valid, reason
