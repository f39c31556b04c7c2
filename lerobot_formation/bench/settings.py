"""The bench library's typed inputs: what a controller is made with, and one bench run's settings
(the CLIs build them from their arguments)."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot_formation.core.perception.conditions import Conditions


@dataclass(frozen=True)
class ControllerOptions:
    """What a controller factory may read.

    Args:
        policy_path: checkpoint folder of the diffusion controllers.
        candidates: K of the best-of-K controllers ("diffusion-bestof", "diffusion-safe").
        num_inference_steps: DDIM steps (None: the checkpoint's sampler).
        seed_policy: seed of the controllers' noise (diffusion, MPPI).
        overrides: policy config fields every diffusion controller runs with, after its own.
        experiment: a ``policy.replanner.ReplanExperiment`` (ablation settings), or None.
        conditions: the run's realistic conditions: the controllers with a safety layer give it the
            actuator's delay and rate limits and whether obstacles move
            (``controllers.safety_settings``); None: none.
        scenes_move: the scenes give their obstacles' velocities (a scenes file's ``velocities``):
            the safety layer predicts the observed obstacles even without ``moving_obstacles``.
        device: torch device of the diffusion controllers' networks ("cpu", "cuda", "cuda:1"); the
            scenes, the replanner's state and the safety layer stay on the CPU.
    """

    policy_path: str | None = None
    candidates: int = 10
    num_inference_steps: int | None = None
    seed_policy: int = 0
    overrides: dict = field(default_factory=dict)
    experiment: object | None = None
    conditions: Conditions | None = None
    scenes_move: bool = False
    device: str = "cpu"


@dataclass(frozen=True)
class BenchSettings:
    """One bench run's inputs (``lerobot-formation-bench``'s options as a value).

    Args:
        scenes: the main scene set's spec (``random:N``, ``dataset:N``, a file, ...).
        unseen: the unseen scene set's spec, or None.
        seed: first seed of ``random:N``.
        options: what the controllers are made with.
        progress: progress bars (only on a terminal).
        order: the controllers' names in registry order (the tables' columns).
        policy_controllers: the names, in that order, of the controllers that run a checkpoint.
        shard: ``"I/N"``: this run is shard I of N of the scene set (None: the whole set).
    """

    scenes: str
    unseen: str | None = None
    seed: int = 0
    options: ControllerOptions = field(default_factory=ControllerOptions)
    progress: bool = False
    order: tuple[str, ...] = ()
    policy_controllers: tuple[str, ...] = ()
    shard: str | None = None


# the meta entries of results.json that shards of one run share (merge) and a resumed run keeps
RUN_SETTINGS = (
    "scenes",
    "unseen",
    "seed",
    "policy_path",
    "candidates",
    "num_inference_steps",
    "conditions",
    "unseen_conditions",
)
