"""Grid cost-to-go (a navigation function) for B scenes at once.

A plain potential field has local minima in front of obstacle clusters (SPEC: "a purely local field
also stalls"). PAC's path check uses this cost-to-go to pick the detour side that actually leads to
the goal. It is a wavefront (8-connected, diagonal cost sqrt 2) on a ``resolution`` grid where
cells within r + ``inflate`` of an obstacle cost ``wall_cost`` times more, so it is finite
everywhere, even inside the inflated zone, and has no local minima.

Reads: the value of a point is its nearest cell's, or with ``bilinear`` the bilinear interpolation of
the four cells around it: with (i, j) the cell at or below and left of the point and (tx, ty) in
[0, 1]^2 its offset from that cell in cells,

    V = (1 - tx)(1 - ty) V[i, j] + tx (1 - ty) V[i + 1, j] + (1 - tx) ty V[i, j + 1] + tx ty V[i + 1, j + 1],

continuous in the point, where a nearest read jumps by up to a cell's cost at each cell border.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

_SHIFTS = [(-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (-1, 1), (1, -1), (1, 1)]
# Cells per side of the grid: 600 at 0.2 m covers 120 m, more than scenes can span (core.world.scenes keeps
# start and goal within MAX_COORDINATE = 50 m of the origin). Beyond it the wavefront would take hours
# and terabytes (a goal 1e5 m away: 1.8 TiB), so it is refused.
MAX_GRID_CELLS = 600


def grid_size(lo: float, hi: float, resolution: float) -> int:
    """Cells per side of a square grid from ``lo`` to (at least) ``hi`` [m]."""
    return int(np.ceil((hi - lo) / resolution)) + 1


def grid_cell(xy: np.ndarray, origin: float, resolution: float, n: int) -> np.ndarray:
    """Nearest cell (..., 2) int64 of points xy (..., 2) on the grid origin + resolution * [0, n)^2."""
    return np.clip(np.round((xy - origin) / resolution).astype(np.int64), 0, n - 1)


_CORNERS = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], dtype=np.int64)


def bilinear_cells(xy: np.ndarray, origin: float, resolution: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The four cells (P, 4, 2) int64 around points xy (P, 2) on the grid origin + resolution *
    [0, n)^2, in the order of the module docstring's formula, and each point's offset (P, 2) in
    [0, 1]^2 from the first (points off the grid: the border cells)."""
    f = (xy - origin) / resolution
    base = np.clip(np.floor(f), 0, n - 2)
    frac = np.clip(f - base, 0.0, 1.0)
    return base.astype(np.int64)[:, None, :] + _CORNERS[None], frac


def bilinear_mix(corners: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """The module docstring's interpolation (P,) of the values (P, 4) at ``bilinear_cells``."""
    tx, ty = frac[:, 0], frac[:, 1]
    return (
        (1 - tx) * (1 - ty) * corners[:, 0]
        + tx * (1 - ty) * corners[:, 1]
        + (1 - tx) * ty * corners[:, 2]
        + tx * ty * corners[:, 3]
    )


def inflated_cells(
    obstacles: np.ndarray, present: np.ndarray, inflate: float, origin: float, resolution: float, n: int
) -> np.ndarray:
    """Grid cells (B, n, n) bool within r + ``inflate`` of an obstacle (B, M, 3) that is ``present``
    (B, M); the walls of both grid wavefronts (this module's cost-to-go, ``validity.passage_exists``)."""
    axis = origin + resolution * np.arange(n)
    X, Y = np.meshgrid(axis, axis, indexing="ij")  # (n, n)
    walls = np.zeros((len(obstacles), n, n), dtype=bool)
    for m in range(obstacles.shape[1]):  # loop over the few obstacle slots, not scenes
        ox, oy, r = (obstacles[:, m, k][:, None, None] for k in range(3))
        walls |= ((X - ox) ** 2 + (Y - oy) ** 2 < (r + inflate) ** 2) & present[:, m][:, None, None]
    return walls


def neighbour_slices(dx: int, dy: int, n: int) -> tuple[tuple[slice, ...], tuple[slice, ...]]:
    """Index pairs (src, dst) of (B, n, n) grids such that ``a[dst]`` cell (i, j) faces ``a[src]`` cell
    (i + dx, j + dy): one wavefront relaxation toward a neighbour is one array operation."""
    src = (slice(None), slice(max(dx, 0), n + min(dx, 0)), slice(max(dy, 0), n + min(dy, 0)))
    dst = (slice(None), slice(max(-dx, 0), n + min(-dx, 0)), slice(max(-dy, 0), n + min(-dy, 0)))
    return src, dst


@dataclass
class CostToGo:
    """Cost-to-go fields of B scenes on a common grid.

    Attributes:
        value: (B, n, n) cost-to-go [m-equivalent].
        origin: lower-left corner of the grid [m].
        resolution: cell size [m].
    """

    value: np.ndarray
    origin: float
    resolution: float

    def __getitem__(self, idx) -> CostToGo:
        return CostToGo(self.value[idx], self.origin, self.resolution)

    def cell(self, xy: np.ndarray) -> np.ndarray:
        return grid_cell(xy, self.origin, self.resolution, self.value.shape[-1])

    def carrot(self, xy: np.ndarray, n_cells: int) -> np.ndarray:
        """Follow steepest descent ``n_cells`` cells from each point xy (B, 2) -> target points (B, 2)."""
        B, n = len(xy), self.value.shape[-1]
        ij = self.cell(xy)
        bi = np.arange(B)
        sh = np.asarray(_SHIFTS)
        for _ in range(n_cells):
            nb = np.clip(ij[:, None, :] + sh[None], 0, n - 1)  # (B, 8, 2)
            vals = self.value[bi[:, None], nb[..., 0], nb[..., 1]]
            here = self.value[bi, ij[:, 0], ij[:, 1]]
            best = np.argmin(vals, axis=1)
            better = vals[bi, best] < here
            ij = np.where(better[:, None], nb[bi, best], ij)
        return self.origin + self.resolution * ij.astype(np.float64)

    def at(self, xy: np.ndarray, rows: np.ndarray | None = None, bilinear: bool = False) -> np.ndarray:
        """Cost-to-go at points xy (P, 2); point p reads field rows[p] (default: field p); its nearest
        cell, or with ``bilinear`` the four around it (module docstring)."""
        rows = np.arange(len(xy)) if rows is None else rows
        if not bilinear:
            ij = self.cell(xy)
            return self.value[rows, ij[:, 0], ij[:, 1]]
        cells, frac = bilinear_cells(xy, self.origin, self.resolution, self.value.shape[-1])
        return bilinear_mix(self.value[np.asarray(rows)[:, None], cells[..., 0], cells[..., 1]], frac)


def _grid(
    obstacles: np.ndarray, goal: np.ndarray, inflate: float, resolution: float, wall_cost: float, bounds
) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Cell costs (B, n, n), the initial values (0 at the goal cell, inf elsewhere), origin and n."""
    lo, hi = bounds
    lo = min(lo, float(goal.min()) - 2.0)
    hi = max(hi, float(goal.max()) + 2.0)
    if not (np.isfinite(lo) and np.isfinite(hi)) or (hi - lo) / resolution >= MAX_GRID_CELLS:
        raise ValueError(
            f"cost_to_go: goals {np.asarray(goal).min():.4g}..{np.asarray(goal).max():.4g} m need a grid over "
            f"[{lo:.4g}, {hi:.4g}] m, more than {MAX_GRID_CELLS} cells of {resolution:g} m per side; keep goals "
            "within 50 m of the origin (core.world.scenes.MAX_COORDINATE)"
        )
    n = grid_size(lo, hi, resolution)
    B = len(goal)
    # few obstacle slots; padded ones have r = 0 and sit far away
    walls = inflated_cells(obstacles, obstacles[..., 2] > 0, inflate, lo, resolution, n)
    cost = np.where(walls, wall_cost, np.float64(1.0))
    value = np.full((B, n, n), np.inf)
    gi = grid_cell(goal, lo, resolution, n)
    value[np.arange(B), gi[:, 0], gi[:, 1]] = 0.0
    return cost, value, lo, n


def _relax(value: np.ndarray, cost: np.ndarray, resolution: float):
    """Wavefront rounds in place (each relaxes all 8 neighbours once); yields the number of rounds done."""
    n = value.shape[-1]
    # a step from a cell to its neighbour costs the step's length times the cell's cost
    edges = [
        (src, dst, resolution * (np.sqrt(2.0) if dx and dy else 1.0) * cost[dst])
        for (dx, dy) in _SHIFTS
        for src, dst in [neighbour_slices(dx, dy, n)]
    ]
    for rounds in range(1, 8 * n + 1):
        for src, dst, w in edges:
            np.minimum(value[dst], value[src] + w, out=value[dst])
        yield rounds


def cost_to_go(
    obstacles: np.ndarray,
    goal: np.ndarray,
    inflate: float = 0.7,
    resolution: float = 0.2,
    wall_cost: float = 30.0,
    bounds: tuple[float, float] = (-3.0, 9.0),
) -> CostToGo:
    """Wavefront cost-to-go to ``goal`` (B, 2) around ``obstacles`` (B, M, 3), run to convergence."""
    cost, value, lo, _ = _grid(obstacles, goal, inflate, resolution, wall_cost, bounds)
    prev = value.copy()
    for rounds in _relax(value, cost, resolution):  # converged: a round (one in ten checked) changed nothing
        if rounds % 10 == 1 and np.array_equal(prev, value):
            break
        if rounds % 10 == 0:
            prev = value.copy()
    return CostToGo(value, lo, resolution)


def cost_to_go_at(
    obstacles: np.ndarray,
    goal: np.ndarray,
    points: np.ndarray,
    rows: np.ndarray | None = None,
    inflate: float = 0.7,
    resolution: float = 0.2,
    wall_cost: float = 30.0,
    bounds: tuple[float, float] = (-3.0, 9.0),
    bilinear: bool = False,
) -> np.ndarray:
    """``cost_to_go(...).at(points, rows, bilinear)`` (P,), bit for bit, without finishing the whole field.

    After r wavefront rounds a cell holds the cheapest path of at most r steps (or better); a path of
    more steps costs at least (r + 1) * ``resolution`` * (the cheapest cell cost). So once every queried
    cell's value is below that bound, no later round can lower it, and the wavefront stops there: at
    a few metres from the goal that is well before the far corners of the grid have converged (the
    best-of-K scorer queries one start and a few dozen chunk ends per replan).
    """
    cost, value, lo, n = _grid(obstacles, goal, inflate, resolution, wall_cost, bounds)
    points = np.asarray(points, np.float64)
    rows = np.arange(len(points)) if rows is None else np.asarray(rows)
    if bilinear:  # the four cells around each point are read, and must be exact
        cells, frac = bilinear_cells(points, lo, resolution, n)
        ij, rows = cells.reshape(-1, 2), np.repeat(rows, 4)
    else:
        ij = grid_cell(points, lo, resolution, n)
    step = resolution * min(1.0, wall_cost)  # the cheapest step
    for rounds in _relax(value, cost, resolution):
        q = value[rows, ij[:, 0], ij[:, 1]]
        if (q < (rounds + 1) * step * (1.0 - 1e-9)).all():  # margin: the bound's own rounding
            break
    return bilinear_mix(q.reshape(-1, 4), frac) if bilinear else q


# PAC's route (``core.controllers.pac.PACConfig``'s defaults): the route hint
# (``core.encodings.route_encoding``) plans the same cost-to-go, carrot and path check.
PAC_INFLATE = (
    0.75  # [m] obstacle inflation of PAC's field and path check: bar half-width + agent radius + margin
)
PAC_LOOKAHEAD = 3.0  # [m] path-blocked check length
PAC_PATH_INFLATE = 0.9  # [m] obstacle inflation of the cost-to-go: avoids gaps the square can't turn in
PAC_CARROT_CELLS = 5  # detour target: this many cost-to-go cells (0.2 m) down the gradient


def path_blocked(
    p: np.ndarray, goal: np.ndarray, obstacles: np.ndarray, lookahead: float, inflate: float
) -> np.ndarray:
    """PAC's path check (B,) bool: the segment from p (B, 2) toward the goal (B, 2), up to ``lookahead``
    metres, passes within r + ``inflate`` of an obstacle (B, M, 3) centre (radius 0: an empty slot)."""
    to_goal = goal - p
    dist_goal = np.linalg.norm(to_goal, axis=-1)
    u = to_goal / np.maximum(dist_goal, 1e-9)[:, None]
    rel = obstacles[..., :2] - p[:, None, :]  # (B, M, 2)
    t = np.einsum("bmk,bk->bm", rel, u)  # along the segment
    seg = np.minimum(dist_goal, lookahead)[:, None]
    closest = np.sqrt(np.maximum(np.sum(rel * rel, -1) - t * t, 0.0))
    R = obstacles[..., 2] + inflate
    return ((t > 0) & (t < seg + R) & (closest < R) & (obstacles[..., 2] > 0)).any(axis=1)


def batch_bounds(goal: np.ndarray, bounds: tuple[float, float] = (-3.0, 9.0)) -> tuple[float, float]:
    """The grid bounds ``cost_to_go`` uses for goals (B, 2): passing them for any subset of these goals
    gives a field on the same grid (``refresh_rows``)."""
    return min(bounds[0], float(goal.min()) - 2.0), max(bounds[1], float(goal.max()) + 2.0)


def refresh_rows(
    ctg: CostToGo, rows: np.ndarray, obstacles: np.ndarray, goal: np.ndarray, bounds, **kw
) -> None:
    """Recompute the fields ``rows`` of ``ctg`` (built with ``bounds = batch_bounds(all goals)``) for new
    ``obstacles`` (len(rows), M, 3) and their ``goal`` (len(rows), 2), in place, on the same grid."""
    fresh = cost_to_go(obstacles, goal, bounds=bounds, **kw)
    if fresh.value.shape[1:] != ctg.value.shape[1:] or fresh.origin != ctg.origin:
        raise ValueError(
            f"refresh_rows: grid {fresh.value.shape[1:]} at {fresh.origin} is not {ctg.value.shape[1:]}"
        )
    ctg.value[rows] = fresh.value


# Per-scene fields by scene (canonical obstacles + goal bytes): PAC and the route encoding of the same
# scene share one field, and an episode's steps reuse it. A 61 x 61 field is 30 kB.
_SCENE_FIELDS: OrderedDict[bytes, CostToGo] = OrderedDict()
SCENE_CACHE_SIZE = 1024


def _canonical(obstacles: np.ndarray) -> np.ndarray:
    """The present obstacles (m, 3) of one scene (M, 3) (radius > 0), sorted by x then y."""
    present = obstacles[obstacles[:, 2] > 0]
    return present[np.lexsort((present[:, 1], present[:, 0]))]


class SceneFields:
    """Cost-to-go fields of B scenes, each computed on its own grid (``cost_to_go`` of that scene alone),
    so a scene's field does not depend on which other scenes share its batch. ``carrot`` and indexing
    as ``CostToGo``; rows on the same grid are looked up in one array operation."""

    def __init__(self, fields: list[CostToGo]):
        self.fields = fields

    @classmethod
    def build(cls, obstacles: np.ndarray, goal: np.ndarray, inflate: float = 0.7) -> SceneFields:
        """Fields of scenes ``obstacles`` (B, M, 3) (radius 0: an empty slot), ``goal`` (B, 2), cached."""
        fields = []
        for b in range(len(goal)):
            obs = _canonical(np.asarray(obstacles[b], np.float64))
            g = np.asarray(goal[b], np.float64)
            key = obs.tobytes() + g.tobytes() + np.float64(inflate).tobytes()
            field = _SCENE_FIELDS.get(key)
            if field is None:
                field = cost_to_go(obs[None], g[None], inflate=inflate)
                _SCENE_FIELDS[key] = field
                if len(_SCENE_FIELDS) > SCENE_CACHE_SIZE:
                    _SCENE_FIELDS.popitem(last=False)
            else:
                _SCENE_FIELDS.move_to_end(key)
            fields.append(field)
        return cls(fields)

    def __len__(self) -> int:
        return len(self.fields)

    def __getitem__(self, idx) -> SceneFields:
        return SceneFields([self.fields[i] for i in np.arange(len(self.fields))[idx]])

    def carrot(self, xy: np.ndarray, n_cells: int) -> np.ndarray:
        """``CostToGo.carrot`` of each point xy (B, 2) on its own scene's field -> (B, 2)."""
        out = np.empty((len(xy), 2))
        groups: dict[tuple, list[int]] = {}
        for b, f in enumerate(self.fields):
            groups.setdefault((f.origin, f.resolution, f.value.shape[-1]), []).append(b)
        for (origin, resolution, _), rows in groups.items():
            stacked = CostToGo(np.concatenate([self.fields[b].value for b in rows]), origin, resolution)
            out[rows] = stacked.carrot(xy[rows], n_cells)
        return out
