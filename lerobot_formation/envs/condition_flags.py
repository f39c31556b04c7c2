"""``--env.<field> VALUE`` command-line flags of the realistic conditions (``core.perception.conditions``) for
``lerobot-formation-bench`` and ``lerobot-formation-generate``: the same names as the env config's
fields (``lerobot-eval --env.sensing_range=3``), so one spelling works everywhere. Each flag's type and
help come from the field's declaration in ``core.perception.conditions.Conditions``."""

from __future__ import annotations

import argparse

from lerobot_formation.core.perception.conditions import (
    CONDITION_FIELDS,
    Conditions,
    condition_help,
    condition_kind,
)


def _bool(text: str) -> bool:
    low = text.strip().lower()
    if low in ("true", "1", "yes"):
        return True
    if low in ("false", "0", "no"):
        return False
    raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")


def _kind(name: str):
    kind = condition_kind(name)
    return _bool if kind is bool else kind


def add_condition_arguments(
    ap: argparse.ArgumentParser, title: str = "realistic conditions (docs/conditions.md), all off by default"
) -> None:
    """Add ``--env.<field> VALUE`` for every field of ``Conditions`` (all off by default), in an
    argument group titled ``title``."""
    group = ap.add_argument_group(title)
    for name in CONDITION_FIELDS:
        kind = _kind(name)
        metavar = {_bool: "BOOL", int: "N"}.get(kind, "X")
        group.add_argument(
            f"--env.{name}",
            dest=f"env_{name}",
            type=kind,
            default=None,
            metavar=metavar,
            help=condition_help(name),
        )


def conditions_from_flags(parsed) -> Conditions:
    """The ``Conditions`` of the parsed ``--env.<field>`` flags (the attributes ``env_<field>`` that
    ``add_condition_arguments`` adds); ``ValueError`` names a bad field and value."""
    given = {name: getattr(parsed, f"env_{name}") for name in CONDITION_FIELDS}
    return Conditions(**{k: v for k, v in given.items() if v is not None})
