"""``--env.<field> VALUE`` command-line flags of the realistic conditions (``core.conditions``) for
``lerobot-formation-bench`` and ``lerobot-formation-generate``: the same names as the env config's
fields (``lerobot-eval --env.sensing_range=3``), so one spelling works everywhere."""

from __future__ import annotations

import argparse
from dataclasses import fields

from lerobot_formation.core.conditions import CONDITION_FIELDS, Conditions

_HELP = {
    "sensing_range": "[m] obstacles are observed once some agent came within this range of their surface",
    "obstacle_memory": "keep obstacles once seen (true/false)",
    "obstacle_noise": "[m] std of the per-step noise on observed obstacle centres and radii",
    "pose_noise": "[m] std of the per-step noise on the observed midpoint pose (heading: rad)",
    "action_noise": "std of the multiplicative noise on each command component",
    "action_delay": "[control steps] commands take effect this many steps late",
    "max_linear_accel": "[m/s^2] rate limit on v",
    "max_angular_accel": "[rad/s^2] rate limit on omega",
    "moving_obstacles": "how many of a scene's obstacles move",
    "obstacle_speed": "[m/s] speed of the moving obstacles",
}


def _bool(text: str) -> bool:
    low = text.strip().lower()
    if low in ("true", "1", "yes"):
        return True
    if low in ("false", "0", "no"):
        return False
    raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")


def _kind(name: str):
    default = getattr(Conditions(), name)
    if isinstance(default, bool):
        return _bool
    if isinstance(default, int):
        return int
    return float


def add_condition_arguments(
    ap: argparse.ArgumentParser, title: str = "realistic conditions (docs/conditions.md), all off by default"
) -> None:
    """Add ``--env.<field> VALUE`` for every field of ``Conditions`` (all off by default), in an
    argument group titled ``title``."""
    group = ap.add_argument_group(title)
    for f in fields(Conditions):
        kind = _kind(f.name)
        metavar = {_bool: "BOOL", int: "N"}.get(kind, "X")
        group.add_argument(
            f"--env.{f.name}",
            dest=f"env_{f.name}",
            type=kind,
            default=None,
            metavar=metavar,
            help=_HELP[f.name],
        )


def conditions_from_flags(parsed) -> Conditions:
    """The ``Conditions`` of the parsed ``--env.<field>`` flags (the attributes ``env_<field>`` that
    ``add_condition_arguments`` adds); ``ValueError`` names a bad field and value."""
    given = {name: getattr(parsed, f"env_{name}") for name in CONDITION_FIELDS}
    return Conditions(**{k: v for k, v in given.items() if v is not None})
