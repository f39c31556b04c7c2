"""The scene container: ``Scenes``, a batch of B scenes (circular obstacles, a goal and a start pose;
SPEC "The world"), padded to M obstacle rows, and the limits a scene keeps.

Where scenes come from: ``core.world.sampling`` (a pure function of a seed, from a distribution of
``core.world.presets``), ``core.world.scene_files`` (scenes files, checked by ``core.world.validity``) and
``scenes_from_frames`` (a dataset's ``scene.*`` values).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

FAR = 1.0e6  # [m] padded obstacle rows sit here, radius 0, so they never touch anything
PAPER_START = (0.0, 0.0, np.pi / 2)  # midpoint pose [x, y, phi] of the paper's start
MAX_GOAL_DISTANCE = 50.0  # [m] farthest goal from the start a scene may have
MAX_COORDINATE = 50.0  # [m] start and goal coordinates within [-MAX_COORDINATE, MAX_COORDINATE]
MAX_OBSTACLE_VALUE = (
    1000.0  # [m] obstacle x, y and r within [-1000, 1000] (no overflow, no padding look-alike)
)
MAX_OBSTACLE_SPEED = 10.0  # [m/s] a scene's moving obstacles (``velocities``) are at most this fast


@dataclass(frozen=True)
class Scenes:
    """A batch of B scenes.

    Attributes:
        obstacles: (B, M, 3) [x, y, r] in metres; padded rows are at (FAR, FAR) with r = 0.
        mask: (B, M) bool, True for real obstacles.
        goal: (B, 2) midpoint goal [m].
        start: (B, 3) midpoint start pose [x, y, phi].
        seeds: (B,) int64 seed of each scene, -1 for scenes given by hand.
        velocities: (B, M, 2) [m/s] each obstacle's velocity at the start (moving obstacles,
            ``core.perception.conditions``), or None: the scenes give none (padded rows and static obstacles 0).
    """

    obstacles: np.ndarray
    mask: np.ndarray
    goal: np.ndarray
    start: np.ndarray
    seeds: np.ndarray = field(default=None)  # type: ignore[assignment]
    velocities: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.seeds is None:
            object.__setattr__(self, "seeds", np.full(len(self.goal), -1, dtype=np.int64))

    def __len__(self) -> int:
        return len(self.goal)

    def __getitem__(self, idx) -> Scenes:
        idx = np.atleast_1d(np.arange(len(self))[idx])
        vel = None if self.velocities is None else self.velocities[idx]
        return Scenes(
            self.obstacles[idx], self.mask[idx], self.goal[idx], self.start[idx], self.seeds[idx], vel
        )

    def to_list(self) -> list[dict]:
        """Scenes as JSON-friendly dicts (the scenes-file format)."""
        out = []
        for b in range(len(self)):
            obs = self.obstacles[b][self.mask[b]]
            out.append(
                {
                    "obstacles": [[float(x), float(y), float(r)] for x, y, r in obs],
                    "goal": [float(v) for v in self.goal[b]],
                    "start": [float(v) for v in self.start[b]],
                }
            )
            if self.velocities is not None:
                out[-1]["velocities"] = [[float(x), float(y)] for x, y in self.velocities[b][self.mask[b]]]
        return out

    def padded(self, M: int) -> Scenes:
        """The same scenes with M obstacle rows (M >= the current count; new rows are padding)."""
        grow = M - self.mask.shape[1]
        mask = np.pad(self.mask, ((0, 0), (0, grow)))
        vel = None if self.velocities is None else np.pad(self.velocities, ((0, 0), (0, grow), (0, 0)))
        return Scenes(_pad(self.obstacles, M), mask, self.goal, self.start, self.seeds, vel)

    def copy(self) -> Scenes:
        vel = None if self.velocities is None else self.velocities.copy()
        return Scenes(
            *(np.array(a, copy=True) for a in (self.obstacles, self.mask, self.goal, self.start, self.seeds)),
            vel,
        )

    @staticmethod
    def concat(parts: list[Scenes]) -> Scenes:
        M = max(p.obstacles.shape[1] for p in parts)
        parts = [p.padded(M) for p in parts]
        return Scenes(
            np.concatenate([p.obstacles for p in parts]),
            np.concatenate([p.mask for p in parts]),
            np.concatenate([p.goal for p in parts]),
            np.concatenate([p.start for p in parts]),
            np.concatenate([p.seeds for p in parts]),
            None
            if all(p.velocities is None for p in parts)
            else np.concatenate([p.velocity_array() for p in parts]),
        )

    def velocity_array(self) -> np.ndarray:
        """(B, M, 2) the obstacles' velocities, zeros where the scenes give none."""
        if self.velocities is None:
            return np.zeros((*self.mask.shape, 2))
        return self.velocities


def _pad(obstacles: np.ndarray, M: int) -> np.ndarray:
    B, m, _ = obstacles.shape
    if m == M:
        return obstacles
    pad = np.zeros((B, M - m, 3))
    pad[..., :2] = FAR
    return np.concatenate([obstacles, pad], axis=1)


def scenes_from_frames(
    obstacles: np.ndarray, goal: np.ndarray, start: np.ndarray, seeds: np.ndarray
) -> Scenes:
    """Rebuild Scenes from a dataset's per-episode ``scene.*`` values (``generate_pac_dataset``):
    obstacles (B, 3 * slots) with r = 0 in unused slots, goal (B, 2), start (B, 3), seeds (B,)."""
    obs = np.asarray(obstacles, dtype=np.float64).reshape(len(goal), -1, 3)
    mask = obs[..., 2] > 0
    obs[~mask] = (FAR, FAR, 0.0)
    return Scenes(obs, mask, np.asarray(goal, np.float64), np.asarray(start, np.float64), np.asarray(seeds))
