"""PAC episodes for the dataset: scenes by seed, simulated batch by batch on the NumPy core
(optionally in worker processes that die with the generating process), successful ones kept in
seed order; and the seeds and episode counts of each shard.

The expert (``EXPERTS``): "pac" drives on what the team perceives (``core.perception.conditions.Perception``);
"privileged" acts on the true world (``rollout(privileged=True)``: every obstacle where it is, with
its velocity), avoids the moving obstacles over the next ``EXPERT_PREDICT`` seconds and compensates
the action delay (``PACController(predict=, delay=)``), while the frames still hold what the team
perceived. Without conditions both are PAC on the true scene. "oracle" plans each episode on the
true simulator before it starts (``core.episodes.oracle``: a search that knows the movers' future and
the noise) and sends its plan; its episodes are the scenes it solved, its frames what the team
perceived and the plan's commands (held 0.5 s each, or route pursuit down the static cost-to-go). "policy" is a controller the caller
builds (``policy_expert``, an ``ExpertFactory``: this layer imports no policy), e.g. a diffusion
checkpoint with its whole safety layer (``bench.controllers.PolicyExpert``, the bench's
"diffusion-safe", told each episode's conditions): the demonstrations of self-imitation, the layer's
choices distilled into the network that proposes them (DAgger under the layer: the states are those
the layer visits, the labels what it sent). It sees what the team perceives, as PAC does; it runs in
the generating process (no workers: torch, one bundle). Its sampling noise is drawn for each
rollout's batch from its seed, so its episodes repeat for the same seeds and ``batch_size``, not
across batch sizes.

Randomized conditions (``randomize``: the ceiling, e.g. a level's conditions): episode seed s gets
``core.perception.conditions.randomized_conditions(ceiling, s // CONDITION_GROUP)``. The engine takes one
``Conditions`` per rollout, so the episodes of a batch that share a group are rolled out together,
one rollout per group; an episode's conditions are a pure function of its seed, whatever the batch
size, the workers or the shards.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from lerobot_formation.core.controllers.pac import PACController
from lerobot_formation.core.controllers.protocol import Controller
from lerobot_formation.core.episodes.oracle import OracleController
from lerobot_formation.core.episodes.rollout import SUCCESS, EpisodeRecords, rollout
from lerobot_formation.core.perception.conditions import Conditions, randomized_conditions
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.core.world.sampling import sample_distribution
from lerobot_formation.core.world.scenes import Scenes
from lerobot_formation.data.dataset_frames import MAX_OBSTACLES, episode_frames

EXPERTS = ("pac", "privileged", "oracle", "policy")
EXPERT_PREDICT = 1.5  # [s] the privileged expert's lookahead for moving obstacles
CONDITION_GROUP = 16  # consecutive seeds sharing one draw of randomized conditions


class ExpertFactory(Protocol):
    """The "policy" expert: ``factory(params, conditions)`` -> a controller for one rollout under
    ``conditions`` (None: none); ``source`` names what it runs (recorded in ``meta/generation.json``)."""

    source: str

    def __call__(self, params: FormationParams, conditions: Conditions | None) -> Controller: ...


def check_expert(expert: str, policy_expert: ExpertFactory | None = None) -> None:
    """ValueError for an unknown expert, or when ``policy_expert`` is given without the "policy"
    expert or missing with it."""
    if expert not in EXPERTS:
        raise ValueError(f"expert must be one of {EXPERTS}, got {expert!r}")
    if (expert == "policy") != (policy_expert is not None):
        raise ValueError(
            f"the 'policy' expert needs a controller factory (policy_expert) and no other expert takes one; "
            f"got expert {expert!r} with policy_expert {policy_expert!r}"
        )


def privileged_expert(params: FormationParams, conditions: Conditions | None) -> PACController:
    """The privileged expert: PAC that avoids moving obstacles over the next ``EXPERT_PREDICT``
    seconds and compensates the conditions' action delay. It must be driven on the true world
    (``rollout(privileged=True)``; ``privileged`` is set on it so the bench does)."""
    on = conditions is not None and conditions.enabled
    controller = PACController(
        params=params, predict=EXPERT_PREDICT, delay=conditions.action_delay if on else 0
    )
    controller.name = "pac-privileged"
    controller.privileged = True
    return controller


def expert_rollout(
    scenes: Scenes,
    params: FormationParams,
    obstacle_encoding: str,
    conditions: Conditions | None,
    expert: str = "pac",
    policy_expert: ExpertFactory | None = None,
) -> EpisodeRecords:
    """The ``expert``'s episodes on ``scenes`` under ``conditions`` (module docstring); under
    conditions the records hold what the team observed (``EpisodeRecords.observations``)."""
    check_expert(expert, policy_expert)
    on = conditions is not None and conditions.enabled
    privileged = expert in ("privileged", "oracle")
    if expert == "policy":
        controller = policy_expert(params, conditions if on else None)
    elif expert == "oracle":
        controller = OracleController(params=params)
    elif privileged:
        controller = privileged_expert(params, conditions)
    else:
        controller = PACController(params=params)
    return rollout(
        scenes,
        controller,
        params,
        conditions=conditions if on else None,
        record_observations=(obstacle_encoding, None) if on else None,
        privileged=privileged,
    )


@dataclass(frozen=True)
class EpisodeRecipe:
    """What a dataset's episodes are made from, beside the team (``FormationParams``) and the seeds:
    the recipe. ``obstacle_encoding``: what the frames record; ``scene_preset``: the seeds' scenes (a
    ``core.world.sampling.sample_distribution`` spec) when no scenes are given; ``scene_slots``: the
    obstacle rows each frame keeps of its scene; ``conditions``: the episodes' fixed conditions (None
    or all off: none), or ``randomize``: the ceiling of conditions drawn per group of seeds (module
    docstring; the two exclude each other); ``expert`` (``EXPERTS``) and, for the "policy" expert, the
    ``policy_expert`` that builds its controllers. Checked once, when made."""

    obstacle_encoding: str = "grid"
    scene_preset: str = "paper"
    scene_slots: int = MAX_OBSTACLES
    conditions: Conditions | None = None
    expert: str = "pac"
    randomize: Conditions | None = None
    policy_expert: ExpertFactory | None = None

    def __post_init__(self) -> None:
        if self.randomize is not None and self.conditions is not None and self.conditions.enabled:
            raise ValueError("randomized conditions and fixed conditions exclude each other: give one")
        if self.randomize is not None and not self.randomize.enabled:
            raise ValueError("randomized conditions need a ceiling with some condition on")
        check_expert(self.expert, self.policy_expert)


def simulate_batch(
    seeds: np.ndarray, scenes: Scenes | None, params: FormationParams, recipe: EpisodeRecipe
) -> tuple[int, list[dict[str, np.ndarray]]]:
    """The ``recipe``'s expert on one batch of scenes (the seeds' scenes of its ``scene_preset``, or
    the given ones), under its ``conditions``, or under randomized conditions up to its ``randomize``
    drawn per group of seeds (module docstring): (attempted, frames of the successful episodes in
    seed order). Runs in a worker process when generation is pipelined."""
    if scenes is None:
        scenes = sample_distribution(seeds, recipe.scene_preset)
    if recipe.randomize is None:
        groups = [(np.arange(len(scenes)), recipe.conditions)]
    else:
        keys = np.asarray(seeds) // CONDITION_GROUP
        groups = [
            (np.flatnonzero(keys == k), randomized_conditions(recipe.randomize, int(k)))
            for k in np.unique(keys)
        ]
    kept = []
    for rows, group_conditions in groups:
        part = scenes if len(groups) == 1 else scenes[rows]
        rec = expert_rollout(
            part, params, recipe.obstacle_encoding, group_conditions, recipe.expert, recipe.policy_expert
        )
        for b in np.flatnonzero(rec.outcome == SUCCESS):
            kept.append((rows[b], episode_frames(rec, part, b, recipe.obstacle_encoding, recipe.scene_slots)))
    kept.sort(key=lambda row_frames: row_frames[0])
    return len(scenes), [frames for _, frames in kept]


class Generator:
    """Collects successful expert episodes in seed order, batch by batch, each made by ``recipe``.

    With ``workers > 0`` the batches are simulated in worker processes, ``workers`` batches ahead,
    while the caller writes: on 2 cores simulation and LeRobot's writer then overlap. The episodes
    and their order do not depend on ``workers``.
    """

    def __init__(
        self,
        params: FormationParams,
        recipe: EpisodeRecipe = EpisodeRecipe(),
        batch_size: int = 256,
        workers: int = 0,
    ):
        if recipe.expert == "policy" and workers:
            raise ValueError(
                f"the 'policy' expert runs in the generating process: workers must be 0, got {workers}"
            )
        self.params = params
        self.recipe = recipe
        self.batch_size = batch_size
        self.workers = workers
        self.attempted = 0
        self.succeeded = 0

    def _batches(self, seeds_iter, scenes_file: Scenes | None):
        while True:
            seeds = np.asarray([next(seeds_iter) for _ in range(self.batch_size)])
            if scenes_file is not None:
                seeds = seeds[seeds < len(scenes_file)]
                if len(seeds) == 0:
                    return
                yield seeds, scenes_file[seeds]
            else:
                yield seeds, None

    def episodes(self, seeds_iter, n: int, scenes_file: Scenes | None = None, progress=None):
        """Yield the frames of successful episodes until n are produced."""
        produced = 0
        batches = self._batches(seeds_iter, scenes_file)
        if self.workers > 0:
            import concurrent.futures
            import multiprocessing

            pool = concurrent.futures.ProcessPoolExecutor(
                self.workers,
                mp_context=multiprocessing.get_context("fork"),
                initializer=_die_with_parent,
                initargs=(os.getpid(),),
            )
            pending = [
                pool.submit(simulate_batch, *bt, self.params, self.recipe)
                for bt in _take(batches, self.workers)
            ]

            def results():
                while pending:
                    out = pending.pop(0).result()
                    for bt in _take(batches, 1):
                        pending.append(pool.submit(simulate_batch, *bt, self.params, self.recipe))
                    yield out

        else:
            pool = None

            def results():
                for bt in batches:
                    yield simulate_batch(*bt, self.params, self.recipe)

        try:
            for attempted, frames_list in results():
                self.attempted += attempted
                self.succeeded += len(frames_list)
                for frames in frames_list:
                    if produced >= n:
                        return
                    produced += 1
                    if progress is not None:
                        progress(1)
                    yield frames
                if produced >= n:
                    return
        finally:
            if pool is not None:
                _stop_pool(pool)


def _die_with_parent(parent_pid: int) -> None:
    """Worker initializer: the worker ends when the generating process does, however it ends.

    On Linux ``prctl(PR_SET_PDEATHSIG, SIGKILL)`` has the kernel kill the worker the moment its parent
    dies (SIGKILL included); a daemon thread also polls ``os.getppid()`` every 0.5 s (other systems,
    and the case where the parent died before the prctl call). Without this a killed generation left
    its worker blocked on the result pipe, holding ~500 MB.
    """
    import signal
    import threading

    if sys.platform.startswith("linux"):
        with contextlib.suppress(Exception):
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG = 1
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # the parent's SystemExit handler is not the worker's
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the parent, which stops the workers

    def watch() -> None:
        while True:
            if os.getppid() != parent_pid:
                os._exit(1)
            time.sleep(0.5)

    if os.getppid() != parent_pid:
        os._exit(1)
    threading.Thread(target=watch, name="die-with-parent", daemon=True).start()


def _stop_pool(pool) -> None:
    """Shut the worker pool down without waiting for running batches: cancel the queued ones and
    terminate the workers (on success they are idle; on an error or a signal they may be mid-batch)."""
    procs = list(getattr(pool, "_processes", {}).values())  # CPython's ProcessPoolExecutor
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        with contextlib.suppress(Exception):
            proc.terminate()
    for proc in procs:
        with contextlib.suppress(Exception):
            proc.join(timeout=5)


def _take(it, k: int) -> list:
    out = []
    for _ in range(k):
        try:
            out.append(next(it))
        except StopIteration:
            break
    return out


# -- shards: shard i of n takes seeds start + i, start + i + n, ... (merged with lerobot-edit-dataset)
def seed_stream(start: int, num_shards: int, shard_index: int):
    s = start + shard_index
    while True:
        yield s
        s += num_shards


def shard_episodes(total: int, num_shards: int, shard_index: int) -> int:
    return total // num_shards + (1 if shard_index < total % num_shards else 0)
