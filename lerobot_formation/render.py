"""Fast RGB rendering of a formation scene with NumPy only (no window, no plotting library).

``Renderer.draw`` rasterises obstacles, the goal region, the agents' paths so far, the formation
edges and the four agents into an (H, W, 3) uint8 image in about a millisecond, so every frame of an
evaluation can be rendered.
"""

from __future__ import annotations

import numpy as np

COLORS = {
    "background": (255, 255, 255),
    "obstacle": (110, 110, 120),
    "goal": (170, 230, 170),
    "edge": (60, 60, 60),
    "leader": (40, 90, 200),
    "follower": (230, 120, 30),
    "path_leader": (150, 175, 235),
    "path_follower": (245, 195, 150),
}


class Renderer:
    """Draw scenes on a fixed square view of the world.

    Args:
        size: image height and width in pixels.
        bounds: (lo, hi) world coordinates shown on both axes [m].
    """

    def __init__(self, size: int = 256, bounds: tuple[float, float] = (-2.0, 8.0)):
        self.size = size
        self.lo, self.hi = bounds
        self.scale = size / (self.hi - self.lo)  # [px / m]
        c = self.lo + (np.arange(size) + 0.5) / self.scale
        # Pixel centres: row 0 is the top of the image (largest y).
        self.px, self.py = np.meshgrid(c, c[::-1])

    def _to_pixel(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        col = np.floor((xy[..., 0] - self.lo) * self.scale).astype(np.int64)
        row = self.size - 1 - np.floor((xy[..., 1] - self.lo) * self.scale).astype(np.int64)
        return row, col

    def _stamp(self, img: np.ndarray, xy: np.ndarray, color: tuple[int, int, int]) -> None:
        row, col = self._to_pixel(np.asarray(xy).reshape(-1, 2))
        ok = (row >= 0) & (row < self.size) & (col >= 0) & (col < self.size)
        img[row[ok], col[ok]] = color

    def _discs(self, img: np.ndarray, centres: np.ndarray, radii: np.ndarray, color) -> None:
        for (x, y), r in zip(
            np.asarray(centres).reshape(-1, 2), np.broadcast_to(radii, len(centres)), strict=True
        ):
            if r <= 0 or not np.isfinite(x):
                continue
            # Only the bounding box of the disc is tested.
            r0, c0 = self._to_pixel(np.array([x - r, y + r]))
            r1, c1 = self._to_pixel(np.array([x + r, y - r]))
            r0, r1 = max(int(r0), 0), min(int(r1) + 1, self.size)
            c0, c1 = max(int(c0), 0), min(int(c1) + 1, self.size)
            if r0 >= r1 or c0 >= c1:
                continue
            inside = (self.px[r0:r1, c0:c1] - x) ** 2 + (self.py[r0:r1, c0:c1] - y) ** 2 <= r * r
            img[r0:r1, c0:c1][inside] = color

    def draw(
        self,
        obstacles: np.ndarray,
        goal: np.ndarray,
        positions: np.ndarray,
        edges: tuple[np.ndarray, np.ndarray],
        paths: np.ndarray | None = None,
        goal_radius: float = 0.3,
        agent_radius: float = 0.1,
        n_leaders: int = 2,
    ) -> np.ndarray:
        """One frame.

        Args:
            obstacles: (M, 3) [x, y, r]; rows with r = 0 are skipped.
            goal: (2,).
            positions: (N, 2) current agent positions, leaders first.
            edges: (edge_i, edge_j) agent index arrays of the formation graph.
            paths: (T, N, 2) positions so far, or None.
        """
        img = np.empty((self.size, self.size, 3), dtype=np.uint8)
        img[:] = COLORS["background"]
        self._discs(img, np.asarray(goal)[None], np.array([goal_radius]), COLORS["goal"])
        obstacles = np.asarray(obstacles)
        self._discs(img, obstacles[:, :2], obstacles[:, 2], COLORS["obstacle"])
        if paths is not None and len(paths):
            self._stamp(img, paths[:, n_leaders:], COLORS["path_follower"])
            self._stamp(img, paths[:, :n_leaders], COLORS["path_leader"])
        s = np.linspace(0.0, 1.0, 24)[:, None, None]
        ei, ej = edges
        seg = positions[ei][None] * (1 - s) + positions[ej][None] * s  # (24, E, 2)
        self._stamp(img, seg, COLORS["edge"])
        r = max(agent_radius, 1.5 / self.scale)
        self._discs(img, positions[n_leaders:], np.array([r]), COLORS["follower"])
        self._discs(img, positions[:n_leaders], np.array([r]), COLORS["leader"])
        return img
