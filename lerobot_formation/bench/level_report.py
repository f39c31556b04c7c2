"""One controller on one level's scenes, for the per-level report scripts (``scripts/collision_report.py``,
``scripts/jerk_sources.py``): the safety layer's setting overrides as command-line flags, the run, the
summary line both print, and a replanner that records what the layer did at every step
(``recording_replanner``).

``run_level`` and ``safety_overrides`` are the library calls (typed arguments); ``add_arguments`` adds
the scripts' shared flags, whose destinations are ``run_flags``' own parameter names (``RUN_FLAGS``),
so a script passes them on by name.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, replace

import numpy as np

from lerobot_formation.core.episodes.levels import TUNING_SEED_START
from lerobot_formation.core.safety.layer import KnownWorld, SafetySettings, known_world


@dataclass
class LevelRun:
    """What ``run_level`` ran and recorded: the controller (its replanner, if any, holds the safety
    layer's counts), the scenes, the records (``core.episodes.rollout.EpisodeRecords``) and the formation's
    parameters."""

    name: str
    level: str
    seed: int
    controller: object
    scenes: object
    records: object
    params: object

    def summary(self, detail: str = "") -> str:
        """success %, collisions, timeouts, ``detail`` (a caller's counts), and the mean jerk and
        control smoothness over the successful episodes (``core.episodes.metrics``)."""
        from lerobot_formation.core.episodes.metrics import episode_metrics
        from lerobot_formation.core.episodes.rollout import COLLISION, SUCCESS, TIMEOUT

        rec = self.records
        ok = rec.outcome == SUCCESS
        motion = "no successful episode"
        if ok.any():
            per = episode_metrics(rec, self.scenes.start, self.scenes.goal)
            motion = f"jerk {np.mean(per['jerk'][ok]):.3f}, smoothness {np.mean(per['control_smoothness'][ok]):.3f}"
        return (
            f"{self.name} on {self.level} ({len(ok)} scenes from seed {self.seed}): success "
            f"{100 * np.mean(ok):.1f} %, collisions {int(np.sum(rec.outcome == COLLISION))}, "
            f"timeouts {int(np.sum(rec.outcome == TIMEOUT))}; {detail + '; ' if detail else ''}{motion}"
        )


def run_level(
    controller_name: str,
    level_name: str,
    scenes: int,
    seed: int = TUNING_SEED_START,
    policy_path: str | None = None,
    candidates: int = 10,
    overrides: dict | None = None,
    max_steps: int | None = None,
    wrap_replanner=None,
) -> LevelRun:
    """Run the bench's controller ``controller_name`` (``bench.controllers.make_controller``, the
    safety layer told the level's conditions as the bench tells it) on ``scenes`` scenes of level
    ``level_name`` from ``seed``, under the level's conditions. ``overrides``: policy config fields
    (``safety_overrides``). ``wrap_replanner(replanner, max_steps)``: a replacement for the
    controller's replanner (e.g. one that records events), built before the run."""
    from lerobot_formation.bench.controllers import make_controller, needs_policy
    from lerobot_formation.bench.scene_sets import level_scenes
    from lerobot_formation.bench.settings import ControllerOptions
    from lerobot_formation.core.episodes.levels import get_level
    from lerobot_formation.core.episodes.rollout import rollout
    from lerobot_formation.core.world.dynamics import FormationParams

    level = get_level(level_name)  # a bad name: ValueError naming the choices
    if needs_policy(controller_name) and not policy_path:
        raise ValueError(f"controller {controller_name!r} needs a policy path, got {policy_path!r}")
    params = FormationParams()
    options = ControllerOptions(
        policy_path=policy_path, candidates=candidates, conditions=level.conditions, overrides=overrides or {}
    )
    controller = make_controller(controller_name, params, options)
    max_steps = max_steps or params.max_steps
    if wrap_replanner is not None:
        if getattr(controller, "replanner", None) is None:
            raise ValueError(f"controller {controller_name!r} has no replanner to record")
        controller.replanner = wrap_replanner(controller.replanner, max_steps)
    level_set = level_scenes(level.name, scenes, seed=seed)
    rec = rollout(level_set, controller, params, max_steps=max_steps, conditions=level.conditions)
    return LevelRun(controller_name, level.name, seed, controller, level_set, rec, params)


# What ``recording_replanner`` records per episode and step (bool): a scheduled replan, a replan the
# filter or the recheck caused (the plan cut short), and what the replan kept: an escape manoeuvre (as
# the replanner counts them), route pursuit's proposal, and whether it was the fallback, nothing
# scored being safe (the widest chunk or manoeuvre, or a stop); the filter's change.
EVENTS = ("replan", "replan_cut", "escape", "proposal", "search", "fallback", "filter")


def recording_replanner(base, max_steps: int):
    """An instance of a ``Replanner`` subclass built like ``base`` (the bench controller's) that runs
    as it does and records, per episode and step, the events of ``EVENTS`` in ``.events`` (name -> (B,
    max_steps + 2) bool) and, at each replan, how many of the scored chunks (the samples, the
    proposal and the lattice search's paths) were safe and how many were scored, in ``.safe_count`` and ``.scored`` ((B, max_steps + 2)
    int, -1 where no replan); B from its first ``act``."""
    import torch

    from lerobot_formation.policy.replanner import Replanner

    class RecordingReplanner(Replanner):
        def reset(self, batch_size=None, device="cpu"):
            super().reset(batch_size, device)
            self.step, self.events = -1, None

        def act(self, env_now, history, rows=None, noise=None):
            rows = torch.arange(len(env_now)) if rows is None else rows
            if self.events is None:
                B, T = (len(env_now) if self.plan is None else len(self.plan)), max_steps + 2
                self.events = {name: np.zeros((B, T), bool) for name in EVENTS}
                self.safe_count, self.scored = np.full((B, T), -1), np.full((B, T), -1)
            self.step += 1
            self._rows = rows.cpu().numpy()
            return super().act(env_now, history, rows, noise)

        def _replan(self, need, view, stacked, noise):
            idx = need.cpu().numpy()
            cut = (self.has_last[need] & (self.executed[need] < self.settings.n_action_steps)).cpu().numpy()
            self._need = idx
            self.events["replan"][idx, self.step] = ~cut
            self.events["replan_cut"][idx, self.step] = cut
            super()._replan(need, view, stacked, noise)

        def choose(self, *args, **kwargs):
            chosen, info = super().choose(*args, **kwargs)
            self.events["escape"][self._need, self.step] = info["escaped"]
            self.events["proposal"][self._need, self.step] = info["proposal_kept"]
            self.events["search"][self._need, self.step] = info["search_kept"]
            self.events["fallback"][self._need, self.step] = info["blocked"]
            self.safe_count[self._need, self.step] = info["safe"].sum(axis=1)
            self.scored[self._need, self.step] = info["safe"].shape[1]
            return chosen, info

        def filter(self, view, action):
            filtered, changed = super().filter(view, action)
            self.events["filter"][self._rows, self.step] = changed
            return filtered, changed

    out = RecordingReplanner(base.settings, base.layer.settings, base.sampler, base.experiment)
    out.config = base.config
    out.step, out.events = -1, None
    return out


SAFETY_FLAGS = (
    "safety_margin",
    "horizon",
    "chunk_smoothing",
    "mover_uncertainty",
    "layer_ignores_noise",
    "layer_ignores_motion",
)


def safety_overrides(
    safety_margin: float | None = None,
    horizon: int | None = None,
    chunk_smoothing: int | None = None,
    mover_uncertainty: float | None = None,
    layer_ignores_noise: bool = False,
    layer_ignores_motion: bool = False,
    world: KnownWorld | None = None,
) -> dict:
    """Policy config fields replacing the checkpoint's safety settings (None / False: the checkpoint's),
    through the one mapping of the layer's settings to config fields
    (``core.safety.layer.SafetySettings.config_fields``): ``safety_margin`` (the settings' ``margin``),
    ``horizon`` (``safety_horizon``; 0: the chunk alone), ``mover_uncertainty`` (0: a mover's
    prediction as exact); ``chunk_smoothing`` (the sampler's, 0: the samples as drawn; it acts with
    K = 1 too). ``layer_ignores_noise`` / ``layer_ignores_motion``: the layer is told ``world`` (what
    the bench tells it of the level, ``core.safety.layer.known_world``; None: nothing) without the
    sensing noise (no smoothing) / without the obstacles' motion (``safety_world``). The settings'
    docs are ``SafetySettings``' and ``KnownWorld``'s."""
    given = {"margin": safety_margin, "horizon": horizon, "mover_uncertainty": mover_uncertainty}
    settings = {name: value for name, value in given.items() if value is not None}
    if layer_ignores_noise or layer_ignores_motion:
        told = world or KnownWorld()
        if layer_ignores_noise:
            told = replace(told, obstacle_noise=0.0, pose_noise=0.0)
        if layer_ignores_motion:
            told = replace(told, moving_obstacles=False)
        settings["world"] = told
    out = SafetySettings.config_fields(**settings)
    if chunk_smoothing is not None:
        out["chunk_smoothing"] = chunk_smoothing
    return out


RUN_FLAGS = ("level", "scenes", "seed", "policy_path", "candidates", "max_steps", *SAFETY_FLAGS)


def run_flags(controller_name: str, wrap_replanner=None, **flags) -> LevelRun:
    """``run_level`` with its settings as the flags of ``add_arguments`` hold them (their destinations,
    ``RUN_FLAGS``): ``level`` and ``scenes``, ``run_level``'s keywords by name (its defaults where a
    flag is left out; an unknown name is refused by name), the safety overrides (``SAFETY_FLAGS``) as
    ``safety_overrides``' keywords, with the world the bench tells the layer of the level."""
    from lerobot_formation.core.episodes.levels import get_level

    safety = {k: flags.pop(k) for k in SAFETY_FLAGS if k in flags}
    level = flags.pop("level")
    world = known_world(get_level(level).conditions)
    return run_level(
        controller_name,
        level,
        flags.pop("scenes"),
        overrides=safety_overrides(**safety, world=world),
        wrap_replanner=wrap_replanner,
        **flags,
    )


def add_arguments(ap: argparse.ArgumentParser, policy_required: bool = False) -> None:
    """The report scripts' shared flags: the checkpoint, the level and its scenes, K, the safety
    overrides (destinations ``SAFETY_FLAGS``, ``safety_overrides``' parameters) and the episode length."""
    ap.add_argument(
        "--policy.path", dest="policy_path", default=None, required=policy_required, help="the checkpoint"
    )
    ap.add_argument("--level", required=True, help="level0 .. level5")
    ap.add_argument("--scenes", type=int, default=100)
    ap.add_argument("--seed", type=int, default=TUNING_SEED_START, help="first scene seed (tuning seeds)")
    ap.add_argument("--candidates", type=int, default=10)
    ap.add_argument("--safety-margin", type=float, default=None, help="the layer's clearance [m]")
    ap.add_argument(
        "--horizon",
        type=int,
        default=None,
        help="steps the layer looks past every chunk: route pursuit, braking where obstacles move (0: none)",
    )
    ap.add_argument(
        "--chunk-smoothing",
        type=int,
        default=None,
        help="passes of the [1, 2, 1] / 4 kernel over every sampled chunk (0: none)",
    )
    ap.add_argument(
        "--mover-uncertainty",
        type=float,
        default=None,
        help="growth of a moving obstacle's predicted radius per second ahead [m/s]",
    )
    ap.add_argument(
        "--layer-ignores-noise", action="store_true", help="the layer is not told the level's sensing noise"
    )
    ap.add_argument(
        "--layer-ignores-motion", action="store_true", help="the layer is not told that obstacles move"
    )
    ap.add_argument("--max-steps", type=int, default=None, help="episode length (default: the env's)")
