"""What a ``formation_diffusion`` checkpoint folder may contain, checked before LeRobot loads it.

A checkpoint holds data only: ``config.json`` (the policy config, parsed by draccus into
``FormationDiffusionConfig``), ``model.safetensors`` and the processors' ``*.safetensors`` (tensors),
and ``policy_preprocessor.json`` / ``policy_postprocessor.json``, the processor pipelines. LeRobot
builds a pipeline step from its JSON entry either by ``registry_name`` (a step class registered in
``ProcessorStepRegistry``) or by ``class``, a dotted import path that it imports and calls with the
entry's ``config``: a path such as ``subprocess.Popen`` would run a command. ``check_processor_configs``
allows only steps registered in ``ProcessorStepRegistry`` (LeRobot's own and this plugin's
``formation_egocentric_*``), by name or by their class path, and refuses anything else naming the
file, the step and the class, before anything is imported or instantiated.

Where it runs: ``FormationDiffusionPolicy.from_pretrained`` (which ``lerobot-eval``, ``lerobot-train
--policy.path`` and resumed runs call before they load the processors) and the plugin's own loader
(``diffusion_controller.load_policy``: the bench, the demo).
"""

from __future__ import annotations

import json
from pathlib import Path

from lerobot_formation.compat.run_checks import ConfigError

PROCESSOR_CONFIGS = ("policy_preprocessor.json", "policy_postprocessor.json")


class UnsafeCheckpointError(ConfigError):
    """A checkpoint file that loading would turn into running code not registered with LeRobot."""


def registered_processor_steps() -> dict[str, type]:
    """LeRobot's ``ProcessorStepRegistry`` (its registered name -> class). This plugin's steps are in it
    once the plugin (or ``policy.checkpoint.load_policy``) has imported the processor module."""
    from lerobot.processor import ProcessorStepRegistry

    return {name: ProcessorStepRegistry.get(name) for name in ProcessorStepRegistry.list()}


def check_processor_config(path: Path, registered: dict[str, type] | None = None) -> None:
    """Raise UnsafeCheckpointError unless every step of the pipeline JSON ``path`` names a registered
    processor step (by ``registry_name``, or by ``class`` equal to a registered class's path)."""
    path = Path(path)
    registered = registered_processor_steps() if registered is None else registered
    class_paths = {f"{c.__module__}.{c.__qualname__}" for c in registered.values()}
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise UnsafeCheckpointError(f"{path} cannot be read as a processor pipeline: {e}") from e
    steps = data.get("steps") if isinstance(data, dict) else None
    if not isinstance(steps, list):
        raise UnsafeCheckpointError(f"{path} is not a processor pipeline (no list 'steps')")
    for i, step in enumerate(steps):
        name = step.get("registry_name") if isinstance(step, dict) else None
        cls = step.get("class") if isinstance(step, dict) else None
        if name is not None and name in registered:
            continue
        if name is None and cls is not None and cls in class_paths:
            continue
        what = (
            f"registry name {name!r}"
            if name is not None
            else f"class {cls!r}"
            if cls
            else f"entry {step!r:.80}"
        )
        raise UnsafeCheckpointError(
            f"{path} step {i} names {what}, which is not a registered LeRobot processor step: refused "
            "(loading it would import and call it); a checkpoint's processors may only use the steps of "
            "ProcessorStepRegistry"
        )


def check_processor_configs(folder: Path) -> None:
    """``check_processor_config`` on each of the checkpoint folder's pipeline files that exists."""
    registered = registered_processor_steps()
    for name in PROCESSOR_CONFIGS:
        if (Path(folder) / name).is_file():
            check_processor_config(Path(folder) / name, registered)
