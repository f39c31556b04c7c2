"""Fast RGB rendering of a formation scene with NumPy only (no window, no plotting library).

``Renderer.draw`` rasterises obstacles, the goal region, the agents' paths so far, the formation
edges and the four agents into an (H, W, 3) uint8 image in about a millisecond, so every frame of an
evaluation can be rendered.

``EpisodeOverlay`` (a gymnasium wrapper, in the env stack ``lerobot-eval`` uses) writes the episode
time on every rendered frame and, on the frame after the ending step, the outcome: success,
collision (and which agent hit) or timeout. The text is drawn with Pillow, which matplotlib and
LeRobot already depend on.
"""

from __future__ import annotations

import functools

import gymnasium as gym
import numpy as np
from PIL import Image, ImageDraw, ImageFont

COLORS = {
    "background": (255, 255, 255),
    "obstacle": (110, 110, 120),
    "obstacle_unsensed": (215, 215, 222),  # not sensed yet: the true obstacle, faint
    "obstacle_trail": (180, 130, 90),  # where a moving obstacle has been
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
        sensed: np.ndarray | None = None,
        obstacle_trails: np.ndarray | None = None,
    ) -> np.ndarray:
        """One frame.

        Args:
            obstacles: (M, 3) [x, y, r] where the obstacles are now (moving ones at their current
                position); rows with r = 0 are skipped.
            goal: (2,).
            positions: (N, 2) current agent positions, leaders first.
            edges: (edge_i, edge_j) agent index arrays of the formation graph.
            paths: (T, N, 2) positions so far, or None.
            sensed: (M,) bool, False for obstacles the team has not sensed yet (drawn faint); None:
                all drawn alike.
            obstacle_trails: (T, M, 2) obstacle centres so far (a moving obstacle's trail), or None.
        """
        img = np.empty((self.size, self.size, 3), dtype=np.uint8)
        img[:] = COLORS["background"]
        self._discs(img, np.asarray(goal)[None], np.array([goal_radius]), COLORS["goal"])
        obstacles = np.asarray(obstacles)
        if obstacle_trails is not None and len(obstacle_trails):
            trails = np.asarray(obstacle_trails, dtype=np.float64)
            self._stamp(img, trails[np.isfinite(trails).all(axis=-1)], COLORS["obstacle_trail"])
        if sensed is None:
            self._discs(img, obstacles[:, :2], obstacles[:, 2], COLORS["obstacle"])
        else:
            sensed = np.asarray(sensed, dtype=bool)
            self._discs(img, obstacles[~sensed, :2], obstacles[~sensed, 2], COLORS["obstacle_unsensed"])
            self._discs(img, obstacles[sensed, :2], obstacles[sensed, 2], COLORS["obstacle"])
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


# The vector env's metadata carries this key (from ``EpisodeOverlay``): its sub-envs render the
# outcome on the frame after the ending step, which ``lerobot_compat.keep_final_eval_frame`` keeps.
FINAL_FRAME_KEY = "formation_final_frame"
OUTCOME_COLORS = {"success": (30, 140, 60), "collision": (200, 40, 40), "timeout": (210, 120, 0)}
MIN_TEXT_SIZE = 64  # [px] smaller frames get no text (it would cover the scene)


@functools.cache
def _font(size: int) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    return ImageFont.load_default(size=size)


def annotate(frame: np.ndarray, stamp: str, outcome: tuple[str, str] | None = None) -> np.ndarray:
    """A copy of ``frame`` (H, W, 3) uint8 with ``stamp`` in a box at the top left and, if given,
    ``outcome`` = (kind, text) as a banner across the bottom in the kind's colour
    (``OUTCOME_COLORS``). Same shape and dtype; frames under ``MIN_TEXT_SIZE`` pixels come back
    unchanged."""
    h, w = frame.shape[:2]
    if min(h, w) < MIN_TEXT_SIZE:
        return frame.copy()
    img = Image.fromarray(frame)
    draw = ImageDraw.Draw(img)
    font = _font(max(10, h // 20))
    pad = max(2, h // 100)
    x0, y0, x1, y1 = draw.textbbox((2 * pad, 2 * pad), stamp, font=font)
    draw.rectangle((x0 - pad, y0 - pad, x1 + pad, y1 + pad), fill=(255, 255, 255), outline=(60, 60, 60))
    draw.text((2 * pad, 2 * pad), stamp, fill=(0, 0, 0), font=font)
    if outcome is not None:
        kind, text = outcome
        _, ty0, _, ty1 = draw.textbbox((0, 0), text, font=font)
        top = h - (ty1 - ty0) - 4 * pad
        draw.rectangle((0, top, w, h), fill=OUTCOME_COLORS[kind])
        draw.text((2 * pad, top + 2 * pad - ty0), text, fill=(255, 255, 255), font=font)
    return np.asarray(img, dtype=np.uint8).copy()


class EpisodeOverlay(gym.Wrapper):
    """Stamps ``render()`` frames of a ``FormationEnv`` with ``t = 12.3 s`` (steps x dt) and, once the
    episode has ended, its outcome.

    Wrap it outside the ``TimeLimit`` (a truncation is the timeout); ``FormationEnvConfig`` does. The
    time counts this wrapper's own steps, so it needs nothing from the env but ``params`` (dt, agent
    names and radius) and, for the agent that hit, its scene and current positions.
    """

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self.metadata = {**env.metadata, FINAL_FRAME_KEY: True}
        self._steps = 0
        self._outcome: tuple[str, str] | None = None

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self._steps, self._outcome = 0, None
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._steps += 1
        if terminated or truncated:
            self._outcome = self._describe(info, terminated)
        return obs, reward, terminated, truncated, info

    @property
    def time_s(self) -> float:
        return self._steps * self.env.unwrapped.params.dt

    def _describe(self, info: dict, terminated: bool) -> tuple[str, str]:
        t = f"t = {self.time_s:.1f} s"
        if info.get("is_success"):
            return "success", f"success: goal reached at {t}"
        if terminated and info.get("is_collision"):
            agent = self._colliding_agent()
            who = f"{agent} hit an obstacle" if agent else "an agent hit an obstacle"
            return "collision", f"collision: {who} at {t}"
        return "timeout", f"timeout: goal not reached by {t}"

    def _colliding_agent(self) -> str | None:
        """The name (L1, L2, F1, F2) of the agent deepest in an obstacle, from the env's last positions."""
        from lerobot_formation.core.world.geometry import agent_clearances

        env = self.env.unwrapped
        positions = np.asarray(env._path[-1])  # (N, 2): what render() draws
        clear = agent_clearances(positions[None], env.scene.obstacles[:1], env.params.agent_radius)[0]
        return env.params.graph.agents[int(np.argmin(clear))] if (clear < 0).any() else None

    def render(self):
        frame = self.env.render()
        if frame is None:
            return None
        return annotate(frame, f"t = {self.time_s:.1f} s", self._outcome)
