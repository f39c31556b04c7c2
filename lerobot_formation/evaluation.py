"""Fast batched closed-loop evaluation: every episode of a scene set runs at once on the core.

``evaluate(controller, scenes)`` steps all live episodes with one ``dynamics.step`` call and one
controller call per control step, then computes the per-episode records. It is the engine behind
``lerobot-formation-bench`` and the dataset generator.
"""

from __future__ import annotations

import numpy as np

from lerobot_formation.core.dynamics import FormationParams
from lerobot_formation.core.rollout import COLLISION, SUCCESS, TIMEOUT, Controller, EpisodeRecords, rollout
from lerobot_formation.core.scene import Scenes


def evaluate(
    controller: Controller,
    scenes: Scenes,
    params: FormationParams | None = None,
    progress: bool = False,
    desc: str | None = None,
) -> EpisodeRecords:
    """Roll ``controller`` out on every scene (batched) and return the records."""
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(scenes), desc=desc or getattr(controller, "name", "eval"), unit="ep")
    try:
        return rollout(scenes, controller, params, progress=bar.update if bar is not None else None)
    finally:
        if bar is not None:
            bar.close()


def basic_summary(rec: EpisodeRecords, scenes: Scenes) -> dict:
    """Success/collision/timeout counts and a per-episode list."""
    n = len(rec)
    per_episode = [
        {
            "seed": int(scenes.seeds[b]),
            "outcome": {SUCCESS: "success", COLLISION: "collision", TIMEOUT: "timeout"}[int(rec.outcome[b])],
            "steps": int(rec.steps[b]),
        }
        for b in range(n)
    ]
    return {
        "n_episodes": n,
        "success_rate": float(np.mean(rec.outcome == SUCCESS)) if n else 0.0,
        "collisions": int(np.sum(rec.outcome == COLLISION)),
        "timeouts": int(np.sum(rec.outcome == TIMEOUT)),
        "episodes": per_episode,
    }
