"""Fast batched closed-loop evaluation: every episode of a scene set runs at once on the core.

``evaluate(controller, scenes)`` steps all live episodes with one ``dynamics.step`` call and one
controller call per control step, then computes the per-episode records. It is the engine behind
``lerobot-formation-bench``, the ablation and sweep scripts and the dataset generator.
"""

from __future__ import annotations

from lerobot_formation.core.controllers.protocol import Controller
from lerobot_formation.core.episodes.rollout import EpisodeRecords, rollout
from lerobot_formation.core.perception.conditions import Conditions
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.core.world.scenes import Scenes


def evaluate(
    controller: Controller,
    scenes: Scenes,
    params: FormationParams | None = None,
    progress: bool = False,
    desc: str | None = None,
    conditions: Conditions | None = None,
) -> EpisodeRecords:
    """Roll ``controller`` out on every scene (batched) under ``conditions`` (None: none) and return
    the records. A controller with ``privileged = True`` (the privileged expert, a reference that sees
    the true world) acts on the true world; every other one on what the team perceives."""
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(scenes), desc=desc or getattr(controller, "name", "eval"), unit="ep")
    try:
        update = bar.update if bar is not None else None
        return rollout(scenes, controller, params, progress=update, conditions=conditions)
    finally:
        if bar is not None:
            bar.close()
