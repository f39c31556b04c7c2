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
origin facing +y).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

FAR = 1.0e6  # [m] padded obstacle rows sit here, radius 0, so they never touch anything
PAPER_START = (0.0, 0.0, np.pi / 2)  # midpoint pose [x, y, phi] of the paper's start
# Seed ranges of the evaluation protocols (disjoint, like diffusion_policy's train/test seeds).
DATASET_SEED_START = 0
UNSEEN_SEED_START = 1_000_000


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
    formation_radius: float = 1.118  # [m] farthest agent from the midpoint: goal margin
    start_margin: float = 0.2  # [m] clearance each start agent must keep
    grid_resolution: float = 0.1  # [m] passage check
    chunk: int = 64  # candidates drawn per rng call

    def __post_init__(self) -> None:
        lo, hi = self.n_obstacles
        if not 0 <= lo <= hi:
            raise ValueError(f"n_obstacles must be a range 0 <= lo <= hi, got {self.n_obstacles}")
        if not 0 < self.radius[0] <= self.radius[1]:
            raise ValueError(f"radius range must satisfy 0 < lo <= hi, got {self.radius}")
        if not self.centre_low < self.centre_high:
            raise ValueError(
                f"centre range must satisfy low < high, got {self.centre_low}, {self.centre_high}"
            )


@dataclass(frozen=True)
class Scenes:
    """A batch of B scenes.

    Attributes:
        obstacles: (B, M, 3) [x, y, r] in metres; padded rows are at (FAR, FAR) with r = 0.
        mask: (B, M) bool, True for real obstacles.
        goal: (B, 2) midpoint goal [m].
        start: (B, 3) midpoint start pose [x, y, phi].
        seeds: (B,) int64 seed of each scene, -1 for scenes given by hand.
    """

    obstacles: np.ndarray
    mask: np.ndarray
    goal: np.ndarray
    start: np.ndarray
    seeds: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.seeds is None:
            object.__setattr__(self, "seeds", np.full(len(self.goal), -1, dtype=np.int64))

    def __len__(self) -> int:
        return len(self.goal)

    def __getitem__(self, idx) -> Scenes:
        idx = np.atleast_1d(np.arange(len(self))[idx])
        return Scenes(self.obstacles[idx], self.mask[idx], self.goal[idx], self.start[idx], self.seeds[idx])

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
        return out

    @staticmethod
    def concat(parts: list[Scenes]) -> Scenes:
        M = max(p.obstacles.shape[1] for p in parts)
        obstacles = np.concatenate([_pad(p.obstacles, M) for p in parts])
        mask = np.concatenate([np.pad(p.mask, ((0, 0), (0, M - p.mask.shape[1]))) for p in parts])
        return Scenes(
            obstacles,
            mask,
            np.concatenate([p.goal for p in parts]),
            np.concatenate([p.start for p in parts]),
            np.concatenate([p.seeds for p in parts]),
        )


def _pad(obstacles: np.ndarray, M: int) -> np.ndarray:
    B, m, _ = obstacles.shape
    if m == M:
        return obstacles
    pad = np.zeros((B, M - m, 3))
    pad[..., :2] = FAR
    return np.concatenate([obstacles, pad], axis=1)


def scenes_from_list(items: list[dict], config: SceneConfig | None = None, check: bool = True) -> Scenes:
    """Build Scenes from dicts ``{"obstacles": [[x, y, r], ...], "goal": [x, y], "start"?: [x, y, phi]}``."""
    config = config or SceneConfig()
    if not isinstance(items, list) or not items:
        raise ValueError(f"expected a non-empty list of scenes, got {type(items).__name__} {items!r:.80}")
    M = max(1, max(len(s.get("obstacles", [])) if isinstance(s, dict) else 0 for s in items))
    B = len(items)
    obstacles = np.zeros((B, M, 3))
    obstacles[..., :2] = FAR
    mask = np.zeros((B, M), dtype=bool)
    goal = np.zeros((B, 2))
    start = np.tile(np.asarray(config.start, dtype=np.float64), (B, 1))
    for b, s in enumerate(items):
        if not isinstance(s, dict) or "obstacles" not in s or "goal" not in s:
            raise ValueError(f"scene {b} must be a dict with keys 'obstacles' and 'goal', got {s!r:.120}")
        try:
            obs = np.asarray(s["obstacles"], dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise ValueError(
                f"scene {b}: obstacles must be [[x, y, r], ...], got {s['obstacles']!r:.120}"
            ) from e
        if obs.size:
            if obs.ndim != 2 or obs.shape[1] != 3:
                raise ValueError(
                    f"scene {b}: obstacles must be [[x, y, r], ...], got {s['obstacles']!r:.120}"
                )
            obstacles[b, : len(obs)] = obs
            mask[b, : len(obs)] = True
        g = np.asarray(s["goal"], dtype=np.float64)
        if g.shape != (2,):
            raise ValueError(f"scene {b}: goal must be [x, y], got {s['goal']!r}")
        goal[b] = g
        if "start" in s:
            st = np.asarray(s["start"], dtype=np.float64)
            if st.shape != (3,):
                raise ValueError(f"scene {b}: start must be [x, y, phi], got {s['start']!r}")
            start[b] = st
    scenes = Scenes(obstacles, mask, goal, start)
    if check:
        check_scenes(scenes, config)
    return scenes


def check_scenes(scenes: Scenes, config: SceneConfig | None = None) -> None:
    """Raise ValueError naming the first impossible scene: NaN, negative radius, obstacle over the
    start formation, or a goal inside an obstacle."""
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
    from lerobot_formation.core.formation_graph import FormationGraph

    tmpl = np.asarray(FormationGraph().template)
    start_agents = _start_agents(scenes.start, tmpl)  # (B, N, 2)
    gap = _gap(start_agents, scenes.obstacles) - config.agent_radius  # (B, N, M)
    hit = (gap < 0) & scenes.mask[:, None, :]
    if hit.any():
        b, n, m = np.argwhere(hit)[0]
        raise ValueError(
            f"scene {b}: obstacle {m} {scenes.obstacles[b, m].tolist()} lies over the start formation "
            f"(agent {n} at {start_agents[b, n].round(3).tolist()})"
        )
    g = _gap(scenes.goal[:, None, :], scenes.obstacles)[:, 0]  # (B, M)
    inside = (g < 0) & scenes.mask
    if inside.any():
        b, m = np.argwhere(inside)[0]
        raise ValueError(
            f"scene {b}: goal {scenes.goal[b].tolist()} lies inside obstacle {m} {scenes.obstacles[b, m].tolist()}"
        )


def _gap(points: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
    """Distance from points (B, P, 2) to obstacle surfaces (B, M, 3) -> (B, P, M)."""
    d = points[:, :, None, :] - obstacles[:, None, :, :2]
    return np.sqrt(np.sum(d * d, axis=-1)) - obstacles[:, None, :, 2]


def _start_agents(start: np.ndarray, template: np.ndarray) -> np.ndarray:
    """Template agent positions at the start pose, (B, N, 2). Body frame: y along the heading."""
    phi = start[:, 2] - np.pi / 2
    c, s = np.cos(phi), np.sin(phi)
    x = template[None, :, 0] * c[:, None] - template[None, :, 1] * s[:, None]
    y = template[None, :, 0] * s[:, None] + template[None, :, 1] * c[:, None]
    return np.stack([x, y], axis=-1) + start[:, None, :2]


def _cheap_reason(cand: Scenes, config: SceneConfig) -> np.ndarray:
    """Reason codes of the geometric checks: 0 ok, 1 start formation covered, 2 obstacle near goal."""
    from lerobot_formation.core.formation_graph import FormationGraph

    tmpl = np.asarray(FormationGraph().template)
    agents = _start_agents(cand.start, tmpl)
    start_gap = _gap(agents, cand.obstacles) - config.agent_radius - config.start_margin
    mid_gap = _gap(cand.start[:, None, :2], cand.obstacles)[:, 0] - config.half_width - config.agent_radius
    covered = ((start_gap < 0).any(axis=(1, 2))) | ((mid_gap < 0).any(axis=1))
    goal_gap = _gap(cand.goal[:, None, :], cand.obstacles)[:, 0] - config.formation_radius
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
    n = int(np.ceil((hi - lo) / res)) + 1
    axis = lo + res * np.arange(n)
    X, Y = np.meshgrid(axis, axis, indexing="ij")  # (n, n)
    inflate = config.half_width + config.agent_radius
    free = np.ones((len(scenes), n, n), dtype=bool)
    for m in range(scenes.obstacles.shape[1]):  # loop over the few obstacle slots, not scenes
        ox, oy, r = (scenes.obstacles[:, m, k][:, None, None] for k in range(3))
        inside = (X - ox) ** 2 + (Y - oy) ** 2 < (r + inflate) ** 2
        free &= ~(inside & scenes.mask[:, m][:, None, None])
    B = len(scenes)
    si = np.clip(np.round((scenes.start[:, :2] - lo) / res).astype(int), 0, n - 1)
    gi = np.clip(np.round((scenes.goal - lo) / res).astype(int), 0, n - 1)
    reach = np.zeros_like(free)
    reach[np.arange(B), si[:, 0], si[:, 1]] = True
    reach &= free
    goal_free = free[np.arange(B), gi[:, 0], gi[:, 1]]
    for it in range(4 * n):
        grown = reach.copy()
        grown[:, 1:, :] |= reach[:, :-1, :]
        grown[:, :-1, :] |= reach[:, 1:, :]
        grown[:, :, 1:] |= reach[:, :, :-1]
        grown[:, :, :-1] |= reach[:, :, 1:]
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


def _draw_candidates(rng: np.random.Generator, config: SceneConfig) -> tuple[np.ndarray, np.ndarray]:
    C = config.chunk
    M = config.n_obstacles[1]
    count = rng.integers(config.n_obstacles[0], config.n_obstacles[1] + 1, size=C)
    r = rng.uniform(config.radius[0], config.radius[1], size=(C, M))
    xy = rng.uniform(config.centre_low, config.centre_high, size=(C, M, 2))
    mask = np.arange(M)[None, :] < count[:, None]
    obstacles = np.concatenate([xy, r[..., None]], axis=-1)
    obstacles[~mask] = (FAR, FAR, 0.0)
    return obstacles, mask


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
    B, M = len(seeds), config.n_obstacles[1]
    rngs = [np.random.default_rng(int(s)) for s in seeds]
    out_obs = np.zeros((B, M, 3))
    out_mask = np.zeros((B, M), dtype=bool)
    pending = np.arange(B)
    report = report if report is not None else SamplingReport()
    for _ in range(1000):
        draws = [_draw_candidates(rngs[b], config) for b in pending]
        obs = np.concatenate([d[0] for d in draws])  # (P*C, M, 3)
        mask = np.concatenate([d[1] for d in draws])
        P, C = len(pending), config.chunk
        cand = Scenes(
            obs,
            mask,
            np.tile(np.asarray(config.goal, dtype=np.float64), (P * C, 1)),
            np.tile(np.asarray(config.start, dtype=np.float64), (P * C, 1)),
        )
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
            else:
                still.append(b)
        pending = np.asarray(still, dtype=np.int64)
        if len(pending) == 0:
            break
    else:
        raise RuntimeError(
            f"no valid scene found for seeds {seeds[pending][:5].tolist()}: impossible SceneConfig?"
        )
    return Scenes(
        out_obs,
        out_mask,
        np.tile(np.asarray(config.goal, dtype=np.float64), (B, 1)),
        np.tile(np.asarray(config.start, dtype=np.float64), (B, 1)),
        seeds.copy(),
    )


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
    """Read a scenes JSON file; errors name the file and the problem."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError as e:
        raise ValueError(f"scenes file {path} does not exist") from e
    except json.JSONDecodeError as e:
        raise ValueError(f"scenes file {path} is not valid JSON: {e}") from e
    if not isinstance(data, dict) or "scenes" not in data:
        raise ValueError(f"scenes file {path} must hold an object with key 'scenes', got {str(data)[:80]!r}")
    try:
        return scenes_from_list(data["scenes"], config)
    except ValueError as e:
        raise ValueError(f"scenes file {path}: {e}") from e


def save_scenes(scenes: Scenes, path: str | os.PathLike) -> None:
    """Write scenes as JSON (written to a temporary file, then renamed into place)."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps({"scenes": scenes.to_list()}, indent=1))
    os.replace(tmp, path)
