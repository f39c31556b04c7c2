"""The bench's scene sets: ``random:N``, ``<preset>:N``, ``hard:N``, ``<mix>:N``, ``levelK:N``,
``dataset:N`` or a scenes file.

``<mix>:N`` (``core.world.presets.SCENE_MIXES``: ``structures``, ``mixed-hard``) draws seed s from preset
``mix[s % len(mix)]``; ``levelK:N`` the first N scenes of a graded level (``lerobot_formation.core.episodes.levels``),
from the level's own first seed unless a seed is given. A scene set runs under its own conditions
(``scene_set_conditions``): a level's, else the ``--env.<field>`` flags.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lerobot_formation.core.episodes.levels import Level, get_level
from lerobot_formation.core.perception.conditions import Conditions
from lerobot_formation.core.world.presets import HARD_PRESETS, SCENE_MIXES, SCENE_PRESETS, scene_preset
from lerobot_formation.core.world.sampling import (
    UNSEEN_SEED_START,
    SamplingReport,
    sample_mixed,
    sample_scenes,
)
from lerobot_formation.core.world.scene_files import load_scenes
from lerobot_formation.core.world.scenes import Scenes, scenes_from_frames


def scene_set_level(spec: str) -> Level | None:
    """The level of a ``levelK:N`` spec, else None; ValueError naming an unknown level."""
    kind, colon, _ = spec.partition(":")
    return get_level(kind) if colon and kind.startswith("level") else None


def scene_set_conditions(spec: str, flags: Conditions) -> Conditions:
    """The conditions scene set ``spec`` runs under: a level's own (``levelK:N``), else ``flags`` (the
    ``--env.<field>`` flags). ValueError if ``flags`` turns any condition on for a level, which fixes
    its conditions."""
    level = scene_set_level(spec)
    if level is None:
        return flags
    if flags.enabled:
        raise ValueError(
            f"{spec} fixes its own conditions ({level.conditions.changed() or 'none'}); drop --env flags "
            f"{flags.changed()}"
        )
    return level.conditions


def dataset_scenes(root: str | Path, n: int) -> Scenes:
    """Scenes of the first n episodes of a dataset made by ``generate_pac_dataset``."""
    import pyarrow.parquet as pq

    files = sorted(Path(root).glob("data/*/*.parquet"))
    if not files:
        raise ValueError(f"--dataset.root {root} holds no data/*/*.parquet files")
    cols = ["frame_index", "episode_index", "scene.seed", "scene.obstacles", "scene.goal", "scene.start"]
    rows = []
    for f in files:
        try:
            t = pq.read_table(f, columns=cols, filters=[("frame_index", "=", 0)])
        except Exception as e:  # a dataset without scene columns
            raise ValueError(f"{f} lacks the scene.* columns of generate_pac_dataset: {e}") from e
        rows.append(t)
    import pyarrow as pa

    t = pa.concat_tables(rows).sort_by("episode_index").slice(0, n)
    if len(t) < n:
        raise ValueError(f"dataset {root} has {len(t)} episodes, fewer than the {n} asked for")
    return scenes_from_frames(
        np.asarray(t["scene.obstacles"].to_pylist()),
        np.asarray(t["scene.goal"].to_pylist()),
        np.asarray(t["scene.start"].to_pylist()),
        np.asarray(t["scene.seed"].to_pylist()),
    )


def scene_set_presets(spec: str, n: int) -> list[str]:
    """The preset of each of the ``n`` scenes ``parse_scenes(spec, ...)`` gives, for figure titles:
    ``random:N`` -> "paper", ``<preset>:N`` -> that preset, ``hard:N`` -> its presets in
    ``HARD_PRESETS`` order, ``dataset:N`` -> "dataset", a scenes file -> "file"."""
    kind, _, count = spec.partition(":")
    if kind == "hard":
        k = len(HARD_PRESETS)
        sizes = [n // k + (1 if i < n % k else 0) for i in range(k)]
        return [p for p, m in zip(HARD_PRESETS, sizes, strict=True) for _ in range(m)]
    if kind == "random":
        return ["paper"] * n
    if kind in SCENE_PRESETS or kind == "dataset":
        return [kind] * n
    return ["file"] * n


def parse_scenes(
    spec: str,
    seed: int | None,
    dataset_root: str | None = None,
    policy_path: str | None = None,
    report: SamplingReport | None = None,
) -> Scenes:
    """The scenes of ``spec`` (module docstring) from first seed ``seed`` (None: a level's own seed,
    else ``UNSEEN_SEED_START``). ``report`` counts rejected draws."""
    kind, _, count = spec.partition(":")
    level = scene_set_level(spec)
    if level is not None:
        try:
            n = int(count)
        except ValueError as e:
            raise ValueError(f"--scenes {kind}:N needs an integer N, got {spec!r}") from e
        return parse_scenes(f"{level.scenes}:{n}", level.seed if seed is None else seed, report=report)
    seed = UNSEEN_SEED_START if seed is None else seed
    if kind in ("random", "dataset", "hard") or kind in SCENE_PRESETS or kind in SCENE_MIXES:
        try:
            n = int(count)
        except ValueError as e:
            raise ValueError(f"--scenes {kind}:N needs an integer N, got {spec!r}") from e
        if n < 1:
            raise ValueError(f"--scenes {kind}:N needs N >= 1, got {n}")
        if kind == "random":
            return sample_scenes(seed + np.arange(n), report=report)
        if kind in SCENE_PRESETS:
            return sample_scenes(seed + np.arange(n), scene_preset(kind), report=report)
        if kind in SCENE_MIXES:
            return sample_mixed(seed + np.arange(n), SCENE_MIXES[kind], report=report)
        if kind == "hard":  # N/4 scenes of each hard preset, seeds seed.. of each
            k = len(HARD_PRESETS)
            sizes = [n // k + (1 if i < n % k else 0) for i in range(k)]
            return Scenes.concat(
                [
                    sample_scenes(seed + np.arange(m), scene_preset(p), report=report)
                    for p, m in zip(HARD_PRESETS, sizes, strict=True)
                    if m
                ]
            )
        if dataset_root:
            return dataset_scenes(dataset_root, n)
        shipped = Path(policy_path or "") / "dataset_scenes.json"
        if policy_path and shipped.is_file():
            scenes = load_scenes(shipped)
            if len(scenes) < n:
                raise ValueError(f"{shipped} holds {len(scenes)} scenes, fewer than {n}")
            return scenes[:n]
        raise ValueError(
            "--scenes dataset:N needs --dataset.root, or a --policy.path with dataset_scenes.json"
        )
    return load_scenes(spec)


def level_scenes(name: str, n: int, seed: int | None = None) -> Scenes:
    """The first ``n`` scenes of level ``name`` (from ``seed`` instead of the level's own if given)."""
    level = get_level(name)
    if n < 1:
        raise ValueError(f"a level needs n >= 1 scenes, got {n}")
    return parse_scenes(f"{level.scenes}:{n}", level.seed if seed is None else seed)
