"""The one loader for checkpoints written before the current policy config.

Every local ``formation_diffusion`` ``config.json`` that LeRobot loads (``PreTrainedConfig.from_pretrained``:
``lerobot-eval --policy.path``, ``lerobot-train --policy.path``, the bench's loader) is read through
``compat.run_checks.drop_retired_fields`` first (``run_checks.install_config_upgrade``, installed when
the policy config module is imported; one without ``obstacle_encoding`` is refused there, naming
this command); the file itself is left as it is.
``python -m lerobot_formation.compat.old_checkpoints FOLDER`` rewrites ``config.json`` (and the
``policy`` part of ``train_config.json``, which ``lerobot-train --resume`` reads) in place, written to
a temporary file and renamed into position. Either way:

- a retired field (``RETIRED_FIELDS``) is dropped when it holds the value the code now hard-wires;
  any other value is refused, one line naming the field, its value and the wired one (the setting is
  gone, or an experiment setting of ``scripts/ablation.py``, i.e. ``policy.replanner.ReplanExperiment``);
- a safety-layer setting that is fixed now (``FIXED_LAYER_FIELDS``: ``cbf_rate``,
  ``safety_follower_margin``, ``safety_route_proposal``, ``safety_proposal_blend``,
  ``safety_coherence``; ``core.safety.layer``'s constants) is dropped; where its value, or the value
  a config without it ran with, is not the wired one, one warning line names the field, that value
  and the wired one (the checkpoint loads: a K = 1 policy never used them);
- the six flat fields of what the layer knows of the world (``WORLD_FIELDS``:
  ``safety_moving_obstacles``, ``safety_action_delay``, ...) move into ``safety_world``, their values
  kept; ``safety_route_lookahead`` and ``safety_halt_lookahead`` become ``safety_horizon`` (where
  they differ, the route lookahead's value, and a warning naming both);
- a config without a field whose default now turns part of the shipped safety layer on
  (``FIELDS_BEFORE``) was written before that field existed, and ran without it: it gets the value
  it ran with (a K = 1 checkpoint stays K = 1);
- a config without ``obstacle_encoding`` (checkpoints from before the field) gets the encoding whose
  ``observation.environment_state`` size at its default slot count is the feature's size: the only
  place where an encoding is inferred from a size. An ambiguous or unknown size is refused.

Nothing else in the folder is read or changed; no code in the folder is run.
"""

from __future__ import annotations

import json
import os
import sys
from dataclasses import asdict
from pathlib import Path

from lerobot_formation.compat.run_checks import (  # noqa: F401  (re-exported)
    FIELDS_BEFORE,
    FIXED_LAYER_FIELDS,
    LOOKAHEAD_FIELDS,
    RETIRED_FIELDS,
    WORLD_FIELDS,
    OldCheckpointError,
    drop_retired_fields,
)
from lerobot_formation.core.encodings.obstacle_grid import ENCODINGS, environment_state_dim
from lerobot_formation.core.safety.layer import KnownWorld

OBS_ENV_STATE = "observation.environment_state"  # lerobot.utils.constants.OBS_ENV_STATE (no torch here)


def upgrade_policy_config(raw: dict, where: str = "config.json") -> dict:
    """The policy config dict ``raw`` without retired fields, with ``obstacle_encoding`` and every field
    of ``safety_world`` (as LeRobot writes a config; see the module docstring); ``raw`` itself is left
    as it is."""
    out = drop_retired_fields(raw, where)
    try:
        out["safety_world"] = asdict(KnownWorld(**(out.get("safety_world") or {})))
    except (TypeError, ValueError) as e:
        raise OldCheckpointError(f"{where}: {e}") from None
    if out.get("obstacle_encoding") is None:
        env = (out.get("input_features") or {}).get(OBS_ENV_STATE) or {}
        size = tuple(env.get("shape") or ())
        matches = [e for e in ENCODINGS if (environment_state_dim(e, out.get("max_obstacles")),) == size]
        if len(matches) != 1:
            raise OldCheckpointError(
                f"{where}: no obstacle_encoding and observation.environment_state of shape {size} matches "
                f'{matches or "no encoding"}; set "obstacle_encoding" to one of {ENCODINGS}'
            )
        out["obstacle_encoding"] = matches[0]
    return out


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=4) + "\n")
    os.replace(tmp, path)


def upgrade_checkpoint(folder: str | Path) -> list[str]:
    """Rewrite ``folder``'s config.json (and train_config.json's policy) in place; returns the files
    changed. Raises ``OldCheckpointError`` (nothing written) for a value that cannot be carried over."""
    folder = Path(folder)
    config_path = folder / "config.json"
    if not config_path.is_file():
        raise OldCheckpointError(f"{folder} is not a checkpoint folder: no config.json")
    raw = json.loads(config_path.read_text())
    if raw.get("type") != "formation_diffusion":
        raise OldCheckpointError(
            f"{config_path} holds a policy of type {raw.get('type')!r}, not formation_diffusion"
        )
    writes = {config_path: upgrade_policy_config(raw, str(config_path))}
    train_path = folder / "train_config.json"
    if train_path.is_file():
        train = json.loads(train_path.read_text())
        if isinstance(train.get("policy"), dict):
            train["policy"] = upgrade_policy_config(train["policy"], f"{train_path} (policy)")
            writes[train_path] = train
    changed = []
    for path, data in writes.items():
        if data != json.loads(path.read_text()):
            _write_json(path, data)
            changed.append(path.name)
    return changed


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folders", nargs="+", type=Path, help="checkpoint folders (pretrained_model)")
    args = ap.parse_args(argv)
    for folder in args.folders:
        try:
            changed = upgrade_checkpoint(folder)
        except (OldCheckpointError, json.JSONDecodeError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print(f"{folder}: {', '.join(changed) if changed else 'already current'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
