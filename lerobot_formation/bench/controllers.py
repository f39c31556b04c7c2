"""The controllers the bench, the ablation script and the sweeps run, by name.

``CONTROLLER_FACTORIES`` maps a name to a factory ``(name, params, options, policy bundle) ->
controller``, or to the ``"module:function"`` path of one (imported when the controller is first
made, so a new controller is one new file and one line here). A controller needs only
``reset(scenes)`` and ``act(state, idx) -> (len(idx), 2)`` (``core.controllers.protocol.Controller``);
``options`` is a ``ControllerOptions``. Controllers whose name starts with ``diffusion`` run a
checkpoint: the bench asks for ``--policy.path`` and loads it once into ``bundle``. Each of them is
the policy's ``Replanner`` with the checkpoint's config and, for K and the filter, an override
(``dataclasses.replace``, so the config's checks run): "diffusion-policy" runs the config as stored
(the shipped checkpoint's: its safety layer on, best-of-10 and the filter), as ``lerobot-eval
--policy.path`` runs it: not told the run's conditions.
The controllers with a safety layer (best-of-K or the filter) also know the run's world from its
conditions (``ControllerOptions.conditions``, ``safety_settings``: the config's ``safety_world``):
the actuator's delay and rate limits, its sensors' noise stds, and whether obstacles move; what a
robot's designer knows of it, never its noise draws. "route-pursuit-safe" runs the safety layer with no network and no checkpoint
(``bench.layer_controller``; the shipped default's settings, ``core.safety.layer.SafetySettings()``):
the candidates are route pursuit's chunk and the escapes (the baseline of the layer's rows);
"route-pursuit-guided" runs route pursuit's chunk moved by the same settings' clearance guidance,
one chunk per replan as "diffusion-guided" samples (the baseline of the guided rows).
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable

from lerobot_formation.bench.settings import ControllerOptions
from lerobot_formation.core.controllers.pac import PACController
from lerobot_formation.core.perception.conditions import Conditions
from lerobot_formation.core.safety.layer import SafetySettings, known_world
from lerobot_formation.core.world.dynamics import FormationParams


def safety_settings(conditions: Conditions | None, scenes_move: bool = False) -> dict:
    """The policy config field of the safety layer's knowledge of a run under ``conditions``:
    ``{"safety_world": core.safety.layer.known_world(conditions, scenes_move)}`` (the actuator's delay
    and acceleration limits, the sensors' noise stds, and whether obstacles move: ``moving_obstacles``
    of the conditions, or ``scenes_move``, the scenes give their obstacles' ``velocities`` as a scenes
    file may). Empty when neither conditions nor moving scenes (the config's own world stays)."""
    world = known_world(conditions, scenes_move)
    return {} if world is None else SafetySettings.config_fields(world=world)


def _diffusion(safety_filter: str | None, best_of_k: bool | None, guided: bool | None = None):
    """A factory of a diffusion controller with the filter ``safety_filter`` and K = --candidates
    (``best_of_k``) or 1; None for both: the checkpoint's own settings. ``guided``: False samples without clearance guidance, True with
    the checkpoint's ``sampling_guidance``, or where it has none ``TUNED_SAMPLING_GUIDANCE`` (chosen on
    tuning seeds), None as the checkpoint says."""

    def factory(name: str, params: FormationParams, options: ControllerOptions, bundle=None):
        from lerobot_formation.bench.diffusion_controller import DiffusionController

        overrides = {}
        if safety_filter is not None:
            overrides = {
                "num_candidates": options.candidates if best_of_k else 1,
                "safety_filter": safety_filter,
            }
            if guided is False:
                overrides["sampling_guidance"] = 0.0
            elif guided:
                from lerobot_formation.policy.checkpoint import load_policy
                from lerobot_formation.policy.configuration_formation_diffusion import TUNED_SAMPLING_GUIDANCE

                bundle = bundle or load_policy(options.policy_path, options.device)
                overrides["sampling_guidance"] = bundle[0].config.sampling_guidance or TUNED_SAMPLING_GUIDANCE
            if best_of_k or safety_filter != "none" or guided:  # a safety layer: it knows the run's actuator
                overrides.update(safety_settings(options.conditions, options.scenes_move))
        return DiffusionController(
            options.policy_path,
            num_inference_steps=options.num_inference_steps,
            seed=options.seed_policy,
            params=params,
            device=options.device,
            policy_bundle=bundle,
            overrides={**overrides, **options.overrides},
            experiment=options.experiment,
            name=name,
        )

    return factory


def _layer_alone(safety_filter: str, best_of_k: bool):
    """A factory of the safety layer around route pursuit's chunk, no network and no checkpoint
    (``bench.layer_controller.SafetyLayerController``): the shipped default's settings
    (``SafetySettings()``, ``PlanSettings()``) with the filter ``safety_filter``, K = --candidates
    (``best_of_k``) or 1 (then the proposal moved by the clearance guidance), told the run's world
    (``safety_settings``); ``options.overrides`` (policy config fields) of the layer's settings and
    of the plan's apply, the others (a network's) have nothing to act on."""

    def factory(name: str, params: FormationParams, options: ControllerOptions, bundle=None):
        from lerobot_formation.bench.layer_controller import SafetyLayerController
        from lerobot_formation.policy.replanner import PlanSettings

        fields = {**safety_settings(options.conditions, options.scenes_move), **options.overrides}
        safety = SafetySettings(**{"filter": safety_filter, **SafetySettings.from_config_fields(fields)})
        plan = PlanSettings(
            **{
                "num_candidates": options.candidates if best_of_k else 1,
                **PlanSettings.from_config_fields(options.overrides),
            }
        )
        return SafetyLayerController(safety, plan, options.experiment, params, name)

    return factory


def _pac(name, params, options, bundle=None):
    return PACController(params=params)


def _pac_privileged(name, params, options, bundle=None):
    from lerobot_formation.data.pac_episodes import privileged_expert

    return privileged_expert(params, options.conditions)


def _mppi(name, params, options, bundle=None):
    from lerobot_formation.core.controllers.mppi import MPPIConfig, MPPIController

    return MPPIController(MPPIConfig(seed=options.seed_policy), params)


# Controllers by name (see the module docstring): a factory, or the "module:function" path of one.
CONTROLLER_FACTORIES: dict[str, Callable | str] = {
    "pac": _pac,
    "mppi": _mppi,
    "route-pursuit": "lerobot_formation.core.controllers.route_pursuit:make_route_pursuit",
    # a reference, not a baseline: the demonstrator of the students, on the true world (every
    # obstacle, exact, moving ones predicted, the delay compensated)
    "pac-privileged": _pac_privileged,
    "diffusion": _diffusion("none", best_of_k=False, guided=False),  # standard: one sample per replan
    # one sample per replan, guided away from the observed obstacles (sampling_guidance)
    "diffusion-guided": _diffusion("none", best_of_k=False, guided=True),
    "diffusion-bestof": _diffusion("none", best_of_k=True),  # best-of-K (footprint, then progress)
    "diffusion-cbf": _diffusion("cbf", best_of_k=False),  # one sample, CBF filter on every action
    "diffusion-safe": _diffusion("cbf", best_of_k=True),  # best-of-K and the CBF filter
    "diffusion-policy": _diffusion(None, None),  # the checkpoint's config as stored
    # the baseline of "diffusion-safe": its whole safety layer (the shipped default's settings, K's
    # check, escapes, filter, recheck) around route pursuit's proposal, no network, no checkpoint
    "route-pursuit-safe": _layer_alone("cbf", best_of_k=True),
    # the baseline of "diffusion-guided": route pursuit's chunk moved by the same clearance guidance
    "route-pursuit-guided": _layer_alone("none", best_of_k=False),
    # a reference, never a default: a search on the true simulator, each level's ceiling
    "oracle": "lerobot_formation.core.episodes.oracle:make_oracle",
}
# One line per controller for the command lines' --help (``controller_summary``); a controller
# registered without one is listed by its factory.
CONTROLLER_SUMMARIES: dict[str, str] = {
    "pac": "PAC, the datasets' demonstrator, on what the team perceives",
    "mppi": "sampling-based model predictive control on a cost-to-go field",
    "route-pursuit": "learning-free: pure pursuit of a point 1 m down the route hint",
    "pac-privileged": "a reference: PAC on the true world (all obstacles, exact, movers predicted)",
    "diffusion": "standard sampling: one sample per replan, no safety layer",
    "diffusion-guided": "one sample per replan, guided away from the observed obstacles",
    "diffusion-bestof": "best-of-K: K = --candidates samples per replan, the safest kept",
    "diffusion-cbf": "one sample per replan, the CBF filter on every action",
    "diffusion-safe": "the safety layer: best-of-K and the CBF filter",
    "diffusion-policy": "the checkpoint's config as stored (its own K, filter, guidance)",
    "route-pursuit-safe": "diffusion-safe's safety layer around route pursuit, no network",
    "route-pursuit-guided": "route pursuit moved by diffusion-guided's clearance guidance",
    "oracle": "a reference: a search on the true simulator (the map, the movers' future, the noise)",
}
# The safety layer's baselines: a Replanner around route pursuit, no checkpoint (``_layer_alone``)
LAYER_BASELINES = ("route-pursuit-safe", "route-pursuit-guided")
CONTROLLERS = tuple(CONTROLLER_FACTORIES)


def controller_names() -> tuple[str, ...]:
    """The registered names, in registry order (``CONTROLLERS`` plus any registered since import)."""
    return tuple(CONTROLLER_FACTORIES)


def controller_summary(name: str) -> str:
    """One line on controller ``name``: its ``CONTROLLER_SUMMARIES`` entry, else its factory's first
    docstring line, else the factory's name (or ``"module:function"`` path)."""
    summary = CONTROLLER_SUMMARIES.get(name)
    if summary is None:
        factory = CONTROLLER_FACTORIES[name]
        doc = "" if isinstance(factory, str) else (factory.__doc__ or "").strip()
        summary = doc.splitlines()[0] if doc else f"made by {getattr(factory, '__name__', factory)}"
    return summary


def needs_policy(name: str) -> bool:
    """Whether controller ``name`` runs a diffusion checkpoint (``--policy.path``): the ``diffusion``
    ones; the safety layer's baselines (``LAYER_BASELINES``) need none."""
    return name.startswith("diffusion")


def runs_replanner(name: str) -> bool:
    """Whether controller ``name`` runs a ``Replanner`` (a safety layer whose events a report may
    record): the diffusion ones and the layer's baselines (``LAYER_BASELINES``)."""
    return needs_policy(name) or name in LAYER_BASELINES


def make_controller(name: str, params: FormationParams, options: ControllerOptions, bundle=None):
    if name not in CONTROLLER_FACTORIES:
        raise ValueError(f"unknown controller {name!r}; choose from {controller_names()}")
    factory = CONTROLLER_FACTORIES[name]
    if isinstance(factory, str):  # "module:function", imported now
        module, _, attr = factory.partition(":")
        factory = getattr(importlib.import_module(module), attr)
    return factory(name, params, options, bundle)


@dataclasses.dataclass
class PolicyExpert:
    """The dataset generator's "policy" expert (``data.pac_episodes.ExpertFactory``): the controller
    ``controller`` (default "diffusion-safe": best-of-``candidates`` and the CBF filter) of the
    checkpoint at ``policy_path``, its safety layer told each rollout's conditions as the bench tells
    it (``safety_settings``); the checkpoint is loaded once, on the first rollout."""

    policy_path: str
    controller: str = "diffusion-safe"
    candidates: int = 10
    _bundle: tuple | None = dataclasses.field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if not needs_policy(self.controller):
            raise ValueError(
                f"controller {self.controller!r} runs no checkpoint; choose a diffusion controller"
            )

    @property
    def source(self) -> str:
        return f"{self.controller} of {self.policy_path} (K = {self.candidates})"

    def __call__(self, params: FormationParams, conditions: Conditions | None):
        if self._bundle is None:
            from lerobot_formation.policy.checkpoint import load_policy

            self._bundle = load_policy(self.policy_path)
        options = ControllerOptions(
            policy_path=self.policy_path, candidates=self.candidates, conditions=conditions
        )
        return make_controller(self.controller, params, options, self._bundle)
