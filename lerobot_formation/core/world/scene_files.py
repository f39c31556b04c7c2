"""Scenes files: reading (every problem a ``ValueError`` naming the file and the scene) and writing.

Scenes files are JSON: ``{"scenes": [{"obstacles": [[x, y, r], ...], "goal": [x, y],
"start": [x, y, phi]}, ...]}``; ``start`` is optional (default: the paper's start, midpoint at the
origin facing +y), and so is ``velocities`` ([[vx, vy], ...] m/s, one per obstacle: moving obstacles,
``core.perception.conditions``). Loading checks every scene and raises ``ValueError`` naming the scene: only these
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
from pathlib import Path

import numpy as np

from lerobot_formation.core.world.presets import SceneConfig
from lerobot_formation.core.world.scenes import FAR, MAX_OBSTACLE_SPEED, Scenes
from lerobot_formation.core.world.validity import check_scenes

SCENE_KEYS = ("obstacles", "goal", "start", "velocities")  # the keys of a scene in a scenes file
SCENES_FILE_KEYS = ("scenes",)  # the top-level keys of a scenes file
MAX_SCENES_PER_FILE = 20_000  # checking takes ~5 ms a scene: 20 000 scenes ~ 2 min on one core
MAX_SCENES_FILE_BYTES = 64 * 1024 * 1024  # read before parsing; 20 000 scenes take ~10 MB

logger = logging.getLogger(__name__)


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
