"""The controllers the bench, the ablation script and the sweeps run, by name.

``CONTROLLER_FACTORIES`` maps a name to a factory ``(name, params, args, policy bundle) ->
controller``, or to the ``"module:function"`` path of one (imported when the controller is first
made, so a new controller is one new file and one line here). A controller needs only
``reset(scenes)`` and ``act(state, idx) -> (len(idx), 2)`` (``core.rollout.Controller``); ``args``
holds the bench's options (``policy_path``, ``candidates``, ``num_inference_steps``, ``seed_policy``).
Controllers whose name starts with ``diffusion`` run a checkpoint: the bench asks for
``--policy.path`` and loads it once into ``bundle``.
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable

from lerobot_formation.core.dynamics import FormationParams
from lerobot_formation.core.rollout import PACController


def _diffusion(candidates: bool, safety_filter: str | None, adaptive: bool = False):
    """A factory of a diffusion controller: ``candidates`` True takes --candidates, else K = 1;
    ``safety_filter`` None is the world-frame adaptive rule (or standard), "none"/"cbf" the policy's
    own safety layer (core.safety)."""

    def factory(name: str, params: FormationParams, args: argparse.Namespace, bundle=None):
        from lerobot_formation.diffusion_controller import DiffusionController

        return DiffusionController(
            args.policy_path,
            candidates=args.candidates if candidates else 1,
            adaptive=adaptive,
            num_inference_steps=args.num_inference_steps,
            seed=args.seed_policy,
            params=params,
            policy_bundle=bundle,
            safety_filter=safety_filter,
            name=name,
        )

    return factory


def _pac(name, params, args, bundle=None):
    return PACController(params=params)


def _mppi(name, params, args, bundle=None):
    from lerobot_formation.core.mppi import MPPIConfig, MPPIController

    return MPPIController(MPPIConfig(seed=args.seed_policy), params)


# Controllers by name (see the module docstring): a factory, or the "module:function" path of one.
CONTROLLER_FACTORIES: dict[str, Callable | str] = {
    "pac": _pac,
    "mppi": _mppi,
    "route-pursuit": "lerobot_formation.core.route_pursuit:make_route_pursuit",
    "diffusion": _diffusion(False, None),  # standard: one sample per replan
    "diffusion-adaptive": _diffusion(True, None, adaptive=True),  # best-of-K, world-frame cost-to-go rule
    "diffusion-bestof": _diffusion(True, "none"),  # the policy's best-of-K (footprint, then progress)
    "diffusion-cbf": _diffusion(False, "cbf"),  # one sample, CBF filter on every action
    "diffusion-safe": _diffusion(True, "cbf"),  # best-of-K and the CBF filter
}
CONTROLLERS = tuple(CONTROLLER_FACTORIES)


def controller_names() -> tuple[str, ...]:
    """The registered names, in registry order (``CONTROLLERS`` plus any registered since import)."""
    return tuple(CONTROLLER_FACTORIES)


def needs_policy(name: str) -> bool:
    """Whether controller ``name`` runs a diffusion checkpoint (``--policy.path``)."""
    return name.startswith("diffusion")


def make_controller(name: str, params: FormationParams, args: argparse.Namespace, bundle=None):
    if name not in CONTROLLER_FACTORIES:
        raise ValueError(f"unknown controller {name!r}; choose from {controller_names()}")
    factory = CONTROLLER_FACTORIES[name]
    if isinstance(factory, str):  # "module:function", imported now
        module, _, attr = factory.partition(":")
        factory = getattr(importlib.import_module(module), attr)
    return factory(name, params, args, bundle)
