"""Scenes: circular obstacles, a goal and a start pose, sampled from seeds (SPEC "The world").

A scene is a pure function of its seed: ``np.random.default_rng(seed)`` draws candidate scenes in
chunks of ``SceneConfig.chunk`` until one passes the validity check, and the first valid candidate
is the scene. The validity check (``scene_validity``) runs on all candidates of all seeds at once:

1. no obstacle covers the start formation (each start agent keeps ``start_margin`` of clearance,
   and the midpoint keeps the formation half-width);
2. no obstacle sits within the formation's radius (1.12 m for the square) of the goal;
3. a passage exists: a flood fill on a 0.1 m grid, with obstacles inflated by the formation's
   half-width plus the agent radius, connects the start midpoint to the goal.

Scenes files are JSON: ``{"scenes": [{"obstacles": [[x, y, r], ...], "goal": [x, y],
"start": [x, y, phi]}, ...]}``; ``start`` is optional (default: the paper's start, midpoint at the
origin facing +y), and so is ``velocities`` ([[vx, vy], ...] m/s, one per obstacle: moving obstacles,
``core.conditions``). Loading checks every scene and raises ``ValueError`` naming the scene: only these
these keys; numbers only (int or float; not bool, str or null); finite values, positive radii,
obstacle values within ``MAX_OBSTACLE_VALUE``; start
and goal within ``MAX_COORDINATE`` of the origin and the goal within ``MAX_GOAL_DISTANCE`` of the
start (the grids of the passage check and of the controllers' cost-to-go stay small: a team covers
at most v_max * max_steps * dt = 36 m in an episode); no obstacle over the start formation or the
goal; and a passage from the start to the goal (``passage_exists``). A file may hold only the key
``"scenes"``, at most ``MAX_SCENES_FILE_BYTES`` bytes and ``MAX_SCENES_PER_FILE`` scenes (the checks
take ~5 ms per scene); an obstacle listed twice in one scene is logged as a warning.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lerobot_formation.core.dynamics import rotate_body
from lerobot_formation.core.geometry import obstacle_gaps
from lerobot_formation.core.navigation import grid_cell, grid_size, inflated_cells, neighbour_slices

STRUCTURES = ("none", "bend", "trap")
# Obstacle slots of a structure: the bend's 4 walls of BEND_WALL circles (the corner drops a few),
# the trap's back wall of TRAP_BACK circles and its 2 arms of TRAP_ARM circles.
BEND_WALL, TRAP_BACK, TRAP_ARM = 9, 7, 4
STRUCTURE_SLOTS = {"none": 0, "bend": 4 * BEND_WALL, "trap": TRAP_BACK + 2 * TRAP_ARM}
WALL_RADIUS = (0.3, 0.4)  # [m] radius of the circles a structure's walls are built of
FAR = 1.0e6  # [m] padded obstacle rows sit here, radius 0, so they never touch anything
PAPER_START = (0.0, 0.0, np.pi / 2)  # midpoint pose [x, y, phi] of the paper's start
# Seed ranges of the evaluation protocols (disjoint, like diffusion_policy's train/test seeds).
DATASET_SEED_START = 0
UNSEEN_SEED_START = 1_000_000
MAX_GOAL_DISTANCE = 50.0  # [m] farthest goal from the start a scene may have
MAX_COORDINATE = 50.0  # [m] start and goal coordinates within [-MAX_COORDINATE, MAX_COORDINATE]
MAX_OBSTACLE_VALUE = (
    1000.0  # [m] obstacle x, y and r within [-1000, 1000] (no overflow, no padding look-alike)
)
SCENE_KEYS = ("obstacles", "goal", "start", "velocities")  # the keys of a scene in a scenes file
MAX_OBSTACLE_SPEED = 10.0  # [m/s] a scene's moving obstacles (``velocities``) are at most this fast
SCENES_FILE_KEYS = ("scenes",)  # the top-level keys of a scenes file
MAX_SCENES_PER_FILE = 20_000  # checking takes ~5 ms a scene: 20 000 scenes ~ 2 min on one core
MAX_SCENES_FILE_BYTES = 64 * 1024 * 1024  # read before parsing; 20 000 scenes take ~10 MB

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SceneConfig:
    """Distribution of random scenes (SPEC defaults)."""

    n_obstacles: tuple[int, int] = (3, 5)  # inclusive range of the obstacle count
    radius: tuple[float, float] = (0.3, 0.8)  # [m]
    centre_low: float = 1.5  # [m] obstacle centres uniform in [low, high]^2
    centre_high: float = 6.0  # [m]
    goal: tuple[float, float] = (5.0, 5.0)  # [m] midpoint goal
    start: tuple[float, float, float] = PAPER_START
    agent_radius: float = 0.1  # [m]
    half_width: float = 0.5  # [m] half the leader bar: inflation of the passage check (+ agent radius)
    # [m] farthest agent from the midpoint: goal margin. FormationGraph().radius() is sqrt(1.25) =
    # 1.11803...; kept at the rounded 1.118 because the exact value changes the validity of some
    # candidates (8 of the 633,600 paper-layout
    # candidates drawn for seeds 0-2999 and 1,000,000-1,000,299), so it would change scenes.
    formation_radius: float = 1.118
    start_margin: float = 0.2  # [m] clearance each start agent must keep
    grid_resolution: float = 0.1  # [m] passage check
    chunk: int = 64  # candidates drawn per rng call
    # Wider layouts (None / 0 everywhere: the paper's layout above, drawn exactly as before).
    goal_distance: tuple[float, float] | None = None  # [m] goal at this distance from the start ...
    goal_bearing: tuple[float, float] = (0.0, 2 * np.pi)  # [rad] ... in a world direction from this range
    heading_offset: tuple[float, float] = (0.0, 0.0)  # [rad] start heading = goal bearing + offset
    lateral: float = 2.5  # [m] obstacle centres within this distance of the start-goal line
    gate_prob: float = 0.0  # chance of a wall of 4 obstacles across the line with one narrow gap
    gate_gap: tuple[float, float] = (1.3, 1.7)  # [m] surface gap of the gate (the square needs 1.2)
    blocker_prob: float = 0.0  # chance of an obstacle centred on the straight line
    blocker_radius: tuple[float, float] = (0.5, 1.0)  # [m]
    paper_prob: float = 0.0  # chance that a candidate uses the paper's layout instead
    # A structure built of obstacles (``STRUCTURES``): "bend" a narrow corridor with one bend, the
    # team inside its first leg and the goal past its second; "trap" a U of obstacles between start
    # and goal opening toward the team. ``n_obstacles`` more are scattered along the start-goal line.
    structure: str = "none"

    def __post_init__(self) -> None:
        if self.structure not in STRUCTURES:
            raise ValueError(f"structure must be one of {STRUCTURES}, got {self.structure!r}")
        if self.structure != "none" and self.goal_distance is not None:
            raise ValueError(f"structure {self.structure!r} places its own goal; goal_distance must be None")
        lo, hi = self.n_obstacles
        if not 0 <= lo <= hi:
            raise ValueError(f"n_obstacles must be a range 0 <= lo <= hi, got {self.n_obstacles}")
        for name in ("gate_prob", "blocker_prob", "paper_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be a probability in [0, 1], got {getattr(self, name)}")
        if self.goal_distance is not None and not 0 < self.goal_distance[0] <= self.goal_distance[1]:
            raise ValueError(f"goal_distance must satisfy 0 < lo <= hi, got {self.goal_distance}")
        far = max(
            self.goal_distance[1] if self.goal_distance else 0.0,
            float(np.hypot(self.goal[0] - self.start[0], self.goal[1] - self.start[1])),
        )
        if far > MAX_GOAL_DISTANCE:
            raise ValueError(
                f"goals at most {MAX_GOAL_DISTANCE:g} m from the start are supported, got {far:g} m"
            )
        if not 0 < self.radius[0] <= self.radius[1]:
            raise ValueError(f"radius range must satisfy 0 < lo <= hi, got {self.radius}")
        if not self.centre_low < self.centre_high:
            raise ValueError(
                f"centre range must satisfy low < high, got {self.centre_low}, {self.centre_high}"
            )

    @property
    def wide(self) -> bool:
        """False for the paper's layout (fixed goal and start, centres in a square)."""
        return (
            self.goal_distance is not None
            or self.gate_prob > 0
            or self.blocker_prob > 0
            or self.structure != "none"
        )

    @property
    def max_obstacles(self) -> int:
        """Obstacle slots a scene of this distribution can need."""
        return (
            self.n_obstacles[1]
            + (4 if self.gate_prob > 0 else 0)
            + (1 if self.blocker_prob > 0 else 0)
            + STRUCTURE_SLOTS[self.structure]
        )


# Named scene distributions (``--scene-preset`` of the generator, ``<preset>:N`` scene sets of the bench).
# "paper" is SPEC's; the others are what a user meets beyond it: other goals and start headings,
# 0-10 obstacles of radius 0.2-1.0 along the way, narrow gates, obstacles straddling the straight line.
_OTHER_GOALS = dict(goal_distance=(5.0, 9.0), heading_offset=(-np.pi / 2, np.pi / 2))
SCENE_PRESETS: dict[str, SceneConfig] = {
    "paper": SceneConfig(),
    "goals": SceneConfig(**_OTHER_GOALS),
    "dense": SceneConfig(n_obstacles=(8, 10), radius=(0.2, 1.0), **_OTHER_GOALS),
    "gates": SceneConfig(n_obstacles=(0, 3), radius=(0.2, 1.0), gate_prob=1.0, **_OTHER_GOALS),
    "blockers": SceneConfig(n_obstacles=(0, 4), radius=(0.2, 1.0), blocker_prob=1.0, **_OTHER_GOALS),
    "wide": SceneConfig(
        n_obstacles=(0, 10),
        radius=(0.2, 1.0),
        gate_prob=0.25,
        blocker_prob=0.35,
        paper_prob=0.4,
        **_OTHER_GOALS,
    ),
}
HARD_PRESETS = ("gates", "blockers", "dense", "goals")
# Structures no preset above draws (issue 23): a narrow bent corridor, a concave trap, a crowd of more
# obstacles than the policy's encoding observes (12), long routes, goals behind the start.
SCENE_PRESETS.update(
    {
        "bend": SceneConfig(
            n_obstacles=(0, 0), structure="bend", heading_offset=(-0.2, 0.2), gate_gap=(1.8, 2.2)
        ),
        "trap": SceneConfig(n_obstacles=(0, 3), radius=(0.2, 0.6), structure="trap"),
        "crowd": SceneConfig(
            n_obstacles=(20, 30),
            radius=(0.15, 0.3),
            goal_distance=(8.0, 11.0),
            heading_offset=(-np.pi / 4, np.pi / 4),
            lateral=3.0,
        ),
        "long": SceneConfig(
            n_obstacles=(6, 12),
            radius=(0.2, 1.0),
            goal_distance=(14.0, 20.0),
            heading_offset=(-np.pi / 2, np.pi / 2),
            gate_prob=0.3,
            blocker_prob=0.5,
        ),
        "behind": SceneConfig(
            n_obstacles=(2, 6),
            radius=(0.2, 1.0),
            goal_distance=(4.0, 8.0),
            heading_offset=(2 * np.pi / 3, 4 * np.pi / 3),
            blocker_prob=0.5,
        ),
    }
)
STRUCTURE_PRESETS = ("bend", "trap", "crowd", "long", "behind")
# Mixtures of presets, a pure function of the seed: seed s draws from presets[s % len(presets)]
# (``sample_mixed``). "structures": the five above; "mixed-hard": the hard presets (unlike the
# ``hard:N`` scene set, whose blocks of N/4 scenes per preset depend on N).
SCENE_MIXES: dict[str, tuple[str, ...]] = {"structures": STRUCTURE_PRESETS, "mixed-hard": HARD_PRESETS}


def scene_preset(name: str) -> SceneConfig:
    if name not in SCENE_PRESETS:
        raise ValueError(f"scene preset must be one of {tuple(SCENE_PRESETS)}, got {name!r}")
    return SCENE_PRESETS[name]


def mix_max_obstacles(presets: tuple[str, ...]) -> int:
    """Obstacle slots of a mixture's scenes: its largest preset's (``sample_mixed`` pads to it)."""
    return max(scene_preset(name).max_obstacles for name in presets)


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
            ``core.conditions``), or None: the scenes give none (padded rows and static obstacles 0).
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


def _is_number(v) -> bool:
    """int or float (NumPy's too), not bool: JSON's true/false must not pass as 1/0."""
    return isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool | np.bool_)


def _numbers(value, form: str, what: str, b: int) -> np.ndarray:
    """``value`` as floats; ValueError naming scene b unless it is a list of numbers like ``form``."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    n = form.count(",") + 1
    if not isinstance(value, list | tuple) or len(value) != n or not all(_is_number(v) for v in value):
        raise ValueError(f"scene {b}: {what} must be {form} (numbers), got {value!r:.120}")
    try:
        return np.asarray(value, dtype=np.float64)
    except OverflowError as e:  # an int beyond float range
        raise ValueError(f"scene {b}: {what} holds a number out of range: {value!r:.120}") from e


def scenes_from_list(items: list[dict], config: SceneConfig | None = None, check: bool = True) -> Scenes:
    """Build Scenes from dicts ``{"obstacles": [[x, y, r], ...], "goal": [x, y], "start"?: [x, y, phi]}``.

    Every malformed input raises ``ValueError`` naming the scene (wrong keys, types or shapes); with
    ``check`` (default) also every impossible scene (``check_scenes``)."""
    config = config or SceneConfig()
    if not isinstance(items, list | tuple) or not items:
        raise ValueError(f"expected a non-empty list of scenes, got {type(items).__name__} {items!r:.80}")
    parsed = []
    for b, s in enumerate(items):
        if not isinstance(s, dict) or "obstacles" not in s or "goal" not in s:
            raise ValueError(f"scene {b} must be a dict with keys 'obstacles' and 'goal', got {s!r:.120}")
        unknown = sorted(str(k) for k in s if k not in SCENE_KEYS)
        if unknown:
            raise ValueError(
                f"scene {b}: unknown key {unknown[0]!r}; allowed keys: {', '.join(map(repr, SCENE_KEYS))}"
            )
        raw = s["obstacles"]
        if isinstance(raw, np.ndarray):
            raw = raw.tolist()
        if not isinstance(raw, list | tuple):
            raise ValueError(f"scene {b}: obstacles must be a list [[x, y, r], ...], got {raw!r:.120}")
        obs = [
            _numbers(o, "[x, y, r]", f"obstacles must be [[x, y, r], ...]; obstacle {m}", b)
            for m, o in enumerate(raw)
        ]
        goal = _numbers(s["goal"], "[x, y]", "goal", b)
        start = _numbers(s["start"], "[x, y, phi]", "start", b) if "start" in s else None
        vel = _velocities(s["velocities"], len(obs), b) if "velocities" in s else None
        parsed.append((obs, goal, start, vel))
    M = max(1, max(len(obs) for obs, _, _, _ in parsed))
    B = len(items)
    obstacles = np.zeros((B, M, 3))
    obstacles[..., :2] = FAR
    mask = np.zeros((B, M), dtype=bool)
    goal = np.zeros((B, 2))
    start = np.tile(np.asarray(config.start, dtype=np.float64), (B, 1))
    velocities = np.zeros((B, M, 2)) if any(p[3] is not None for p in parsed) else None
    for b, (obs, g, st, vel) in enumerate(parsed):
        if obs:
            obstacles[b, : len(obs)] = np.stack(obs)
            mask[b, : len(obs)] = True
        goal[b] = g
        if st is not None:
            start[b] = st
        if vel is not None and len(vel):
            velocities[b, : len(vel)] = vel
    scenes = Scenes(obstacles, mask, goal, start, velocities=velocities)
    if check:
        check_scenes(scenes, config)
    return scenes


def _velocities(raw, n: int, b: int) -> np.ndarray:
    """A scene's ``velocities`` [[vx, vy], ...] (one per obstacle, finite, at most MAX_OBSTACLE_SPEED)."""
    if isinstance(raw, np.ndarray):
        raw = raw.tolist()
    if not isinstance(raw, list | tuple) or len(raw) != n:
        raise ValueError(
            f"scene {b}: velocities must be a list [[vx, vy], ...] with one entry per obstacle ({n}), got {raw!r:.120}"
        )
    vel = (
        np.stack([_numbers(v, "[vx, vy]", f"velocities; velocity {m}", b) for m, v in enumerate(raw)])
        if n
        else np.zeros((0, 2))
    )
    speed = np.hypot(vel[:, 0], vel[:, 1]) if n else np.zeros(0)
    if not np.all(np.isfinite(speed)) or np.any(speed > MAX_OBSTACLE_SPEED):
        m = int(np.flatnonzero(~(speed <= MAX_OBSTACLE_SPEED))[0])
        raise ValueError(
            f"scene {b}: velocity {m} must be finite and at most {MAX_OBSTACLE_SPEED:g} m/s, got {raw[m]!r}"
        )
    return vel


def scenes_from_frames(
    obstacles: np.ndarray, goal: np.ndarray, start: np.ndarray, seeds: np.ndarray
) -> Scenes:
    """Rebuild Scenes from a dataset's per-episode ``scene.*`` values (``generate_pac_dataset``):
    obstacles (B, 3 * slots) with r = 0 in unused slots, goal (B, 2), start (B, 3), seeds (B,)."""
    obs = np.asarray(obstacles, dtype=np.float64).reshape(len(goal), -1, 3)
    mask = obs[..., 2] > 0
    obs[~mask] = (FAR, FAR, 0.0)
    return Scenes(obs, mask, np.asarray(goal, np.float64), np.asarray(start, np.float64), np.asarray(seeds))


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
    from lerobot_formation.core.formation_graph import FormationGraph

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
    from lerobot_formation.core.formation_graph import FormationGraph

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


@dataclass
class SamplingReport:
    """How many candidate scenes were drawn and why they were rejected."""

    drawn: int = 0
    accepted: int = 0
    rejected_start: int = 0
    rejected_goal: int = 0
    rejected_passage: int = 0

    @property
    def rejected(self) -> int:
        return self.drawn - self.accepted

    @property
    def rejection_rate(self) -> float:
        return self.rejected / max(self.drawn, 1)

    def as_dict(self) -> dict:
        return {
            "drawn": self.drawn,
            "accepted": self.accepted,
            "rejected": self.rejected,
            "rejection_rate": self.rejection_rate,
            "rejected_start_covered": self.rejected_start,
            "rejected_obstacle_near_goal": self.rejected_goal,
            "rejected_no_passage": self.rejected_passage,
        }


def _draw_candidates(
    rng: np.random.Generator, config: SceneConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """C candidate scenes: obstacles (C, M, 3), mask (C, M), goal (C, 2), start (C, 3)."""
    C = config.chunk
    goal = np.tile(np.asarray(config.goal, dtype=np.float64), (C, 1))
    start = np.tile(np.asarray(config.start, dtype=np.float64), (C, 1))
    if not config.wide:  # the paper's layout; these draws define the paper dataset's scenes
        M = config.n_obstacles[1]
        count = rng.integers(config.n_obstacles[0], config.n_obstacles[1] + 1, size=C)
        r = rng.uniform(config.radius[0], config.radius[1], size=(C, M))
        xy = rng.uniform(config.centre_low, config.centre_high, size=(C, M, 2))
        mask = np.arange(M)[None, :] < count[:, None]
        obstacles = np.concatenate([xy, r[..., None]], axis=-1)
        obstacles[~mask] = (FAR, FAR, 0.0)
        return obstacles, mask, goal, start
    if config.structure != "none":
        return _draw_structure(rng, config, start)
    return _draw_wide(rng, config, goal, start)


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance of points p (C, K, 2) to the segments [a, b] (C, 2) -> (C, K)."""
    d = (b - a)[:, None]
    rel = p - a[:, None]
    t = np.clip(np.sum(rel * d, -1) / np.maximum(np.sum(d * d, -1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(rel - t[..., None] * d, axis=-1)


def _draw_structure(rng: np.random.Generator, config: SceneConfig, start: np.ndarray):
    """Candidates of a structure preset (``SceneConfig.structure``), built from touching wall circles.

    bend: legs of lengths L1, L2 in [2.5, 4] m, turned by 60-90 degrees to either side; the walls run
    at gap / 2 + r to each side of the centre line (surface gap ``gate_gap``); wall circles closer than
    that to the other leg (the inner corner) are dropped, the outer walls run on past the corner.
    The team starts at the corridor's mouth facing along it; the goal is 1.8 m past its end.
    trap: a U, back wall across the start-goal line 2.5-3.5 m ahead, arms 1.2-2 m long reaching back
    toward the team, 2.2-3 m between the arms; the goal 2.5-4 m behind the back wall.
    """
    C, M = config.chunk, config.max_obstacles
    n_lo, n_hi = config.n_obstacles
    s0 = start[:, :2]
    bearing = rng.uniform(*config.goal_bearing, size=C)
    offset = rng.uniform(*config.heading_offset, size=C)
    r_wall = rng.uniform(*WALL_RADIUS, size=C)
    u = np.stack([np.cos(bearing), np.sin(bearing)], axis=-1)
    n = np.stack([-u[:, 1], u[:, 0]], axis=-1)
    walls = []  # (C, K, 2) centres, (C, K) kept
    if config.structure == "bend":
        L1, L2 = rng.uniform(2.5, 4.0, size=C), rng.uniform(2.5, 4.0, size=C)
        turn = rng.choice([-1.0, 1.0], size=C) * rng.uniform(np.pi / 3, np.pi / 2, size=C)
        gap = rng.uniform(*config.gate_gap, size=C)
        w = gap / 2 + r_wall  # centre line to wall centres
        u2 = np.stack([np.cos(bearing + turn), np.sin(bearing + turn)], axis=-1)
        n2 = np.stack([-u2[:, 1], u2[:, 0]], axis=-1)
        corner = s0 + L1[:, None] * u
        end = corner + L2[:, None] * u2
        goal = corner + (L2 + 1.8)[:, None] * u2
        frac = np.linspace(0.0, 1.0, BEND_WALL)[None, :]
        s1 = 0.8 + frac * (L1 + w - 0.8)[:, None]  # leg 1 walls, on past the corner
        s2 = -w[:, None] + frac * (L2 + w)[:, None]  # leg 2 walls, from before the corner
        for side in (-1.0, 1.0):
            walls.append(s0[:, None] + s1[..., None] * u[:, None] + (side * w)[:, None, None] * n[:, None])
            walls.append(
                corner[:, None] + s2[..., None] * u2[:, None] + (side * w)[:, None, None] * n2[:, None]
            )
        centres = np.concatenate(walls, axis=1)
        line = np.minimum(_segment_distance(centres, s0, corner), _segment_distance(centres, corner, end))
        kept = line >= w[:, None] - 1e-6
        heading = bearing + offset
    else:  # trap
        depth = rng.uniform(2.5, 3.5, size=C)
        arm = rng.uniform(1.2, 2.0, size=C)
        half = rng.uniform(1.1, 1.5, size=C)
        shift = rng.uniform(-0.5, 0.5, size=C)
        goal_past = rng.uniform(2.5, 4.0, size=C)
        mouth = s0 + depth[:, None] * u + shift[:, None] * n  # middle of the back wall
        across = np.linspace(-1.0, 1.0, TRAP_BACK)[None, :] * half[:, None]
        walls.append(mouth[:, None] + across[..., None] * n[:, None])
        back = np.linspace(1.0, 0.0, TRAP_ARM, endpoint=False)[::-1][None, :] * arm[:, None]
        for side in (-1.0, 1.0):
            walls.append(
                mouth[:, None] - back[..., None] * u[:, None] + (side * half)[:, None, None] * n[:, None]
            )
        centres = np.concatenate(walls, axis=1)
        kept = np.ones(centres.shape[:2], dtype=bool)
        goal = s0 + (depth + goal_past)[:, None] * u
        heading = bearing + offset
    # n_obstacles more along the start-goal line
    dist = np.linalg.norm(goal - s0, axis=-1)
    g_u = (goal - s0) / dist[:, None]
    g_n = np.stack([-g_u[:, 1], g_u[:, 0]], axis=-1)
    count = rng.integers(n_lo, n_hi + 1, size=C)
    along = rng.uniform(0.15, 0.95, size=(C, n_hi))
    lateral = rng.uniform(-config.lateral, config.lateral, size=(C, n_hi))
    r = rng.uniform(config.radius[0], config.radius[1], size=(C, n_hi))
    obstacles = np.zeros((C, M, 3))
    obstacles[..., :2] = FAR
    mask = np.zeros((C, M), dtype=bool)
    K = centres.shape[1]
    obstacles[:, :K, :2] = centres
    obstacles[:, :K, 2] = r_wall[:, None]
    mask[:, :K] = kept
    obstacles[:, K : K + n_hi, :2] = (
        s0[:, None] + (along * dist[:, None])[..., None] * g_u[:, None] + lateral[..., None] * g_n[:, None]
    )
    obstacles[:, K : K + n_hi, 2] = r
    mask[:, K : K + n_hi] = np.arange(n_hi)[None, :] < count[:, None]
    obstacles[~mask] = (FAR, FAR, 0.0)
    start = np.concatenate([start[:, :2], heading[:, None]], axis=1)
    return obstacles, mask, goal, start


def _draw_wide(rng: np.random.Generator, config: SceneConfig, goal: np.ndarray, start: np.ndarray):
    """Candidates of a wide preset: goal at a distance and bearing, obstacles along the start-goal line,
    optional gate and blocker, or (``paper_prob``) the paper's layout."""
    C, M = config.chunk, config.max_obstacles
    n_lo, n_hi = config.n_obstacles
    paper = rng.random(C) < config.paper_prob
    dist = rng.uniform(*config.goal_distance, size=C)
    bearing = rng.uniform(*config.goal_bearing, size=C)
    offset = rng.uniform(*config.heading_offset, size=C)
    count = rng.integers(n_lo, n_hi + 1, size=C)
    along = rng.uniform(0.15, 0.95, size=(C, n_hi))
    across = rng.uniform(-config.lateral, config.lateral, size=(C, n_hi))
    r = rng.uniform(config.radius[0], config.radius[1], size=(C, n_hi))
    gate = rng.random(C) < config.gate_prob
    gate_at = rng.uniform(0.35, 0.7, size=C)
    gate_gap = rng.uniform(*config.gate_gap, size=C)
    gate_shift = rng.uniform(-0.8, 0.8, size=C)
    gate_r = rng.uniform(0.35, 0.6, size=C)
    blocker = rng.random(C) < config.blocker_prob
    blocker_at = rng.uniform(0.3, 0.7, size=C)
    blocker_shift = rng.uniform(-0.3, 0.3, size=C)
    blocker_r = rng.uniform(*config.blocker_radius, size=C)
    # the paper's layout for the chosen candidates (same count and ranges as SceneConfig's defaults)
    p_count = rng.integers(3, 6, size=C)
    p_r = rng.uniform(0.3, 0.8, size=(C, 5))
    p_xy = rng.uniform(1.5, 6.0, size=(C, 5, 2))

    s0 = start[:, :2]
    g = s0 + dist[:, None] * np.stack([np.cos(bearing), np.sin(bearing)], axis=-1)
    u = np.stack([np.cos(bearing), np.sin(bearing)], axis=-1)  # along the line
    n = np.stack([-u[:, 1], u[:, 0]], axis=-1)  # across it
    obstacles = np.zeros((C, M, 3))
    obstacles[..., :2] = FAR
    mask = np.zeros((C, M), dtype=bool)
    k = np.arange(n_hi)[None, :] < count[:, None]
    obstacles[:, :n_hi, :2] = (
        s0[:, None] + along[..., None] * dist[:, None, None] * u[:, None] + across[..., None] * n[:, None]
    )
    obstacles[:, :n_hi, 2] = r
    mask[:, :n_hi] = k
    col = n_hi
    if config.gate_prob > 0:
        # a wall of two touching obstacles on each side of a gap of surface width gate_gap
        centre = s0 + (gate_at * dist)[:, None] * u + gate_shift[:, None] * n
        for j, side in enumerate((-1.0, -1.0, 1.0, 1.0)):
            ring = 1 + (j % 2) * 2  # 1st or 2nd obstacle out from the gap
            off = side * (gate_gap / 2 + ring * gate_r)
            obstacles[:, col, :2] = centre + off[:, None] * n
            obstacles[:, col, 2] = gate_r
            mask[:, col] = gate
            col += 1
    if config.blocker_prob > 0:
        obstacles[:, col, :2] = s0 + (blocker_at * dist)[:, None] * u + blocker_shift[:, None] * n
        obstacles[:, col, 2] = blocker_r
        mask[:, col] = blocker
        col += 1
    # paper-layout candidates: the paper's goal, start and obstacle square
    goal = np.where(paper[:, None], goal, g)
    heading = np.where(paper, start[:, 2], bearing + offset)
    start = np.concatenate([start[:, :2], heading[:, None]], axis=1)
    pm = np.arange(5)[None, :] < p_count[:, None]
    paper_obs = np.zeros((C, M, 3))
    paper_obs[..., :2] = FAR
    paper_obs[:, :5, :2] = p_xy
    paper_obs[:, :5, 2] = p_r
    paper_mask = np.zeros((C, M), dtype=bool)
    paper_mask[:, :5] = pm
    obstacles = np.where(paper[:, None, None], paper_obs, obstacles)
    mask = np.where(paper[:, None], paper_mask, mask)
    obstacles[~mask] = (FAR, FAR, 0.0)
    return obstacles, mask, goal, start


def sample_scenes(seeds, config: SceneConfig | None = None, report: SamplingReport | None = None) -> Scenes:
    """The valid scene of each seed, (B,) seeds -> Scenes of size B.

    Candidates of all seeds are checked together; only the random draws are per seed (each seed has
    its own generator, which is what makes a scene a pure function of its seed).
    """
    config = config or SceneConfig()
    seeds = np.atleast_1d(np.asarray(seeds, dtype=np.int64))
    if seeds.ndim != 1 or len(seeds) == 0:
        raise ValueError(f"seeds must be a non-empty 1-D sequence, got shape {seeds.shape}")
    if (seeds < 0).any():
        raise ValueError(f"seeds must be non-negative, got {seeds[seeds < 0][:5].tolist()}")
    B, M = len(seeds), config.max_obstacles
    rngs = [np.random.default_rng(int(s)) for s in seeds]
    out_obs = np.zeros((B, M, 3))
    out_mask = np.zeros((B, M), dtype=bool)
    out_goal = np.tile(np.asarray(config.goal, dtype=np.float64), (B, 1))
    out_start = np.tile(np.asarray(config.start, dtype=np.float64), (B, 1))
    pending = np.arange(B)
    report = report if report is not None else SamplingReport()
    for _ in range(1000):
        draws = [_draw_candidates(rngs[b], config) for b in pending]
        obs = np.concatenate([d[0] for d in draws])  # (P*C, M, 3)
        mask = np.concatenate([d[1] for d in draws])
        P, C = len(pending), config.chunk
        cand = Scenes(obs, mask, np.concatenate([d[2] for d in draws]), np.concatenate([d[3] for d in draws]))
        valid, reason = _validity_first(cand, config, P, C)
        still = []
        for k, b in enumerate(pending):
            v = np.flatnonzero(valid[k * C : (k + 1) * C])
            rs = reason[k * C : (k + 1) * C]
            n_used = (v[0] + 1) if len(v) else C
            report.drawn += int(n_used)
            report.rejected_start += int(np.sum(rs[:n_used] == 1))
            report.rejected_goal += int(np.sum(rs[:n_used] == 2))
            report.rejected_passage += int(np.sum(rs[:n_used] == 3))
            if len(v):
                report.accepted += 1
                out_obs[b] = obs[k * C + v[0]]
                out_mask[b] = mask[k * C + v[0]]
                out_goal[b] = cand.goal[k * C + v[0]]
                out_start[b] = cand.start[k * C + v[0]]
            else:
                still.append(b)
        pending = np.asarray(still, dtype=np.int64)
        if len(pending) == 0:
            break
    else:
        raise RuntimeError(
            f"no valid scene found for seeds {seeds[pending][:5].tolist()}: impossible SceneConfig?"
        )
    return Scenes(out_obs, out_mask, out_goal, out_start, seeds.copy())


def sample_mixed(seeds, presets: tuple[str, ...], report: SamplingReport | None = None) -> Scenes:
    """The scene of each seed s drawn from preset ``presets[s % len(presets)]``, in the order of
    ``seeds`` (obstacle rows padded to the largest preset's)."""
    seeds = np.atleast_1d(np.asarray(seeds, dtype=np.int64))
    if seeds.ndim != 1 or len(seeds) == 0:
        raise ValueError(f"seeds must be a non-empty 1-D sequence, got shape {seeds.shape}")
    return _sample_assigned(seeds, seeds % len(presets), presets, report)


def distribution_entries(spec: str) -> tuple[str, ...]:
    """The entries of a scene distribution ``spec`` (the generator's ``--scene-preset``): a preset of
    ``SCENE_PRESETS``, a mixture of ``SCENE_MIXES``, or a comma-separated list of those; ValueError
    naming an unknown entry."""
    entries = tuple(e.strip() for e in str(spec).split(","))
    for e in entries:
        if e not in SCENE_PRESETS and e not in SCENE_MIXES:
            raise ValueError(
                f"scene preset {e!r} of {spec!r} is neither a preset {tuple(SCENE_PRESETS)} "
                f"nor a mixture {tuple(SCENE_MIXES)}"
            )
    return entries


def distribution_presets(spec: str) -> tuple[str, ...]:
    """Every preset a scene distribution ``spec`` can draw from (``distribution_entries``)."""
    names = [p for e in distribution_entries(spec) for p in SCENE_MIXES.get(e, (e,))]
    return tuple(dict.fromkeys(names))


def distribution_slots(spec: str) -> int:
    """Obstacle slots a scene of the distribution ``spec`` can need."""
    return max(scene_preset(p).max_obstacles for p in distribution_presets(spec))


def sample_distribution(seeds, spec: str, report: SamplingReport | None = None) -> Scenes:
    """The scene of each seed s of the distribution ``spec`` (``distribution_entries``, k entries):
    entry ``s % k``; an entry that is a mixture draws its preset ``mix[(s // k) % len(mix)]`` (so a
    lone mixture is ``sample_mixed``, and every preset of a mixture in a list is drawn). A single
    preset is ``sample_scenes`` with that preset's config."""
    entries = distribution_entries(spec)
    if len(entries) == 1 and entries[0] in SCENE_PRESETS:
        return sample_scenes(seeds, scene_preset(entries[0]), report)
    seeds = np.atleast_1d(np.asarray(seeds, dtype=np.int64))
    if seeds.ndim != 1 or len(seeds) == 0:
        raise ValueError(f"seeds must be a non-empty 1-D sequence, got shape {seeds.shape}")
    k = len(entries)
    presets = distribution_presets(spec)
    names = []
    for s in seeds.tolist():
        entry = entries[s % k]
        mix = SCENE_MIXES.get(entry)
        names.append(entry if mix is None else mix[(s // k) % len(mix)])
    which = np.array([presets.index(n) for n in names], dtype=np.int64)
    return _sample_assigned(seeds, which, presets, report)


def _sample_assigned(
    seeds: np.ndarray, which: np.ndarray, presets: tuple[str, ...], report: SamplingReport | None
) -> Scenes:
    """The scene of each seed ``seeds[i]`` from preset ``presets[which[i]]``, in the order of
    ``seeds`` (obstacle rows padded to the largest preset's)."""
    parts, order = [], []
    for k, name in enumerate(presets):
        rows = np.flatnonzero(which == k)
        if len(rows):
            parts.append(sample_scenes(seeds[rows], scene_preset(name), report=report))
            order.append(rows)
    M = mix_max_obstacles(presets)
    merged = Scenes.concat([p.padded(M) for p in parts])
    return merged[np.argsort(np.concatenate(order), kind="stable")]


def _validity_first(cand: Scenes, config: SceneConfig, P: int, C: int) -> tuple[np.ndarray, np.ndarray]:
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


def load_scenes(path: str | os.PathLike, config: SceneConfig | None = None) -> Scenes:
    """Read a scenes JSON file; every problem is a ``ValueError`` naming the file (and the scene)."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if path.is_file() and size > MAX_SCENES_FILE_BYTES:
            raise ValueError(
                f"scenes file {path} has {size:,} bytes, more than the {MAX_SCENES_FILE_BYTES:,} a scenes file "
                f"may have (at most {MAX_SCENES_PER_FILE} scenes); split it into several files"
            )
        data = json.loads(path.read_text())
    except FileNotFoundError as e:
        raise ValueError(f"scenes file {path} does not exist") from e
    except json.JSONDecodeError as e:
        raise ValueError(f"scenes file {path} is not valid JSON: {e}") from e
    except UnicodeDecodeError as e:
        raise ValueError(f"scenes file {path} is not UTF-8 text: {e}") from e
    except RecursionError as e:
        raise ValueError(f"scenes file {path} nests its JSON too deeply") from e
    except OSError as e:  # a folder, no permission, ...
        raise ValueError(f"scenes file {path} cannot be read: {e}") from e
    if not isinstance(data, dict) or "scenes" not in data:
        raise ValueError(f"scenes file {path} must hold an object with key 'scenes', got {str(data)[:80]!r}")
    unknown = sorted(str(k) for k in data if k not in SCENES_FILE_KEYS)
    if unknown:
        raise ValueError(
            f"scenes file {path}: unknown top-level key {unknown[0]!r}; allowed keys: "
            f"{', '.join(map(repr, SCENES_FILE_KEYS))}"
        )
    items = data["scenes"]
    if isinstance(items, list) and len(items) > MAX_SCENES_PER_FILE:
        raise ValueError(
            f"scenes file {path} holds {len(items)} scenes, more than the {MAX_SCENES_PER_FILE} a scenes file "
            "may hold (checking takes ~5 ms a scene); split it into several files"
        )
    try:
        scenes = scenes_from_list(items, config)
    except ValueError as e:
        raise ValueError(f"scenes file {path}: {e}") from e
    _warn_repeated_obstacles(scenes, path)
    return scenes


def _warn_repeated_obstacles(scenes: Scenes, path: Path) -> None:
    """Log one warning for a file in which a scene lists the same obstacle [x, y, r] more than once
    (harmless to the simulation, but a sign of a broken scene generator)."""
    repeats, first = 0, None
    for b in range(len(scenes)):
        rows = scenes.obstacles[b][scenes.mask[b]]
        if len(rows) < 2:
            continue
        _, index, counts = np.unique(rows, axis=0, return_index=True, return_counts=True)
        if (counts > 1).any():
            repeats += int((counts - 1).sum())
            if first is None:
                k = int(np.flatnonzero(counts > 1)[0])
                first = (b, int(index[k]), rows[index[k]].tolist(), int(counts[k]))
    if first is not None:
        b, m, row, count = first
        logger.warning(
            "scenes file %s: scene %d lists obstacle %d %s %d times (%d repeated obstacles in the file)",
            path,
            b,
            m,
            row,
            count,
            repeats,
        )


def save_scenes(scenes: Scenes, path: str | os.PathLike) -> None:
    """Write scenes as JSON (written to a temporary file, then renamed into place)."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps({"scenes": scenes.to_list()}, indent=1))
    os.replace(tmp, path)
