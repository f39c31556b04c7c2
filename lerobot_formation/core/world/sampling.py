"""Sampling scenes from seeds (SPEC "The world"); the distributions are ``core.world.presets``.

A scene is a pure function of its seed: ``np.random.default_rng(seed)`` draws candidate scenes in
chunks of ``SceneConfig.chunk`` until one passes the validity check, and the first valid candidate
is the scene. The validity check (``scene_validity``,
``core.world.validity``) runs on all candidates of all seeds at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lerobot_formation.core.world.presets import (
    BEND_WALL,
    SCENE_MIXES,
    SCENE_PRESETS,
    TRAP_ARM,
    TRAP_BACK,
    WALL_RADIUS,
    SceneConfig,
    distribution_entries,
    distribution_presets,
    mix_max_obstacles,
    scene_preset,
)
from lerobot_formation.core.world.scenes import FAR, Scenes
from lerobot_formation.core.world.validity import validity_first

# Seed ranges of the evaluation protocols (disjoint, like diffusion_policy's train/test seeds).
DATASET_SEED_START = 0
UNSEEN_SEED_START = 1_000_000


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
        valid, reason = validity_first(cand, config, P, C)
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
