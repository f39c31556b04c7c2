"""A checkpoint with changed policy options, its weights kept: the start of a fine-tune.

    python scripts/derive_checkpoint.py outputs/train_safe/checkpoints/032000/pretrained_model \
        outputs/cpu_egocentric_init --set egocentric_obstacles=true

``lerobot-train --policy.path=...`` loads the processors saved with the checkpoint, so an option that
adds a processor step (``egocentric_obstacles``) cannot be switched on from the
command line for a fine-tune. This copies the weights, sets the options in config.json and rebuilds
both processors with ``make_formation_diffusion_pre_post_processors`` from the checkpoint's own
normalisation statistics; every other file of the folder (model card, ``dataset_scenes.json``, ...) is
copied as it is. Written to a temporary folder, then renamed into place, so ``dest`` may be the
checkpoint itself: ``--set safety_margin=0.1 --set inference_backend=trace`` on an exported
policy changes those two fields in place; a field of a nested one is ``--set
safety_world.action_delay=1``. The fields are applied with ``dataclasses.replace``, so the config's
checks run.

``--set obstacle_encoding=E`` also widens the network to the new encoding's input (for an encoding
that carries every feature of the old one, e.g. ``nearest+route`` -> ``nearest+route+velocity``;
``lerobot_formation/policy/widen_inputs.py``): the new features get zero weights, so the derived policy
acts as the old one until a fine-tune on a dataset of the new encoding teaches it to use them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
from pathlib import Path

OBS_ENV_STATE = "observation.environment_state"


def parse_value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _same_text(a: Path, b: Path) -> bool:
    return a.is_file() and b.is_file() and a.read_text() == b.read_text()


def _widened(src: Path, cfg, encoding: str):
    """The input features and the weights of the checkpoint ``src`` (config ``cfg``) widened to
    observe ``encoding`` (``policy.widen_inputs``); SystemExit naming the problem otherwise."""
    from lerobot.configs.types import FeatureType, NormalizationMode, PolicyFeature
    from safetensors.torch import load_file

    from lerobot_formation.core.encodings.obstacle_grid import ENCODINGS, get_encoding
    from lerobot_formation.core.perception.observation import STATE_DIM
    from lerobot_formation.policy.widen_inputs import widen_condition_weights

    if encoding not in ENCODINGS:
        raise SystemExit(f"error: --set obstacle_encoding={encoding!r}: not one of {ENCODINGS}")
    if cfg.normalization_mapping.get("ENV") is not NormalizationMode.IDENTITY:
        raise SystemExit(
            "error: --set obstacle_encoding: widening keeps the old features' weights, which needs "
            f"ENV normalization IDENTITY, got {cfg.normalization_mapping.get('ENV')}"
        )
    old, new = get_encoding(cfg.obstacle_encoding), get_encoding(encoding)
    slots = old.slots(cfg.max_obstacles)
    if not new.egocentric or new.slots(cfg.max_obstacles) != slots:
        raise SystemExit(
            f"error: --set obstacle_encoding={encoding!r}: not a widening of {cfg.obstacle_encoding!r}"
        )
    try:
        weights = widen_condition_weights(
            load_file(src / "model.safetensors"),
            old.names(slots),
            new.names(slots),
            STATE_DIM,
            cfg.n_obs_steps,
            cfg.diffusion_step_embed_dim,
        )
    except ValueError as e:
        raise SystemExit(f"error: --set obstacle_encoding={encoding!r}: {e}") from None
    features = dict(cfg.input_features)
    features[OBS_ENV_STATE] = PolicyFeature(type=FeatureType.ENV, shape=(new.dim(cfg.max_obstacles),))
    return features, weights


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    ap.add_argument("checkpoint", type=Path, help="a pretrained_model folder")
    ap.add_argument("dest", type=Path)
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="policy config field")
    args = ap.parse_args(argv)

    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.processor import NormalizerProcessorStep
    from safetensors.torch import save_file

    import lerobot_formation.plugin  # noqa: F401  (registers the policy type and its processor steps)
    from lerobot_formation.policy.processor_formation_diffusion import (
        make_formation_diffusion_pre_post_processors,
    )

    src = args.checkpoint
    if not (src / "model.safetensors").is_file() or not (src / "config.json").is_file():
        raise SystemExit(f"error: {src} is not a checkpoint folder (no model.safetensors / config.json)")
    cfg = PreTrainedConfig.from_pretrained(src)
    old_pre, _ = make_pre_post_processors(cfg, pretrained_path=str(src))
    norm = next((s for s in old_pre.steps if isinstance(s, NormalizerProcessorStep)), None)
    if norm is None:
        raise SystemExit(f"error: {src}/policy_preprocessor.json has no normalizer step")
    raw = json.loads((src / "config.json").read_text())
    names = {f.name for f in dataclasses.fields(cfg)}
    changes = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        head, dot, part = key.partition(".")  # FIELD.PART: a field of a nested settings dataclass
        nested = dot and head in names and dataclasses.is_dataclass(getattr(cfg, head))
        if not sep or (key not in names and not nested):
            raise SystemExit(f"error: --set {item!r}: expected FIELD=VALUE with a {cfg.type} config field")
        if nested:
            try:
                changes[head] = dataclasses.replace(
                    changes.get(head, getattr(cfg, head)), **{part: parse_value(value)}
                )
            except (TypeError, ValueError) as e:
                raise SystemExit(f"error: --set {item!r}: {e}") from None
            raw[head] = dataclasses.asdict(changes[head])
        else:
            changes[key] = raw[key] = parse_value(value)
    weights, stats = None, norm.stats
    if "obstacle_encoding" in changes and changes["obstacle_encoding"] != cfg.obstacle_encoding:
        changes["input_features"], weights = _widened(src, cfg, changes["obstacle_encoding"])
        raw["input_features"][OBS_ENV_STATE]["shape"] = list(changes["input_features"][OBS_ENV_STATE].shape)
        stats = {k: v for k, v in stats.items() if k != OBS_ENV_STATE}  # IDENTITY: no statistics used
    try:
        cfg = dataclasses.replace(cfg, **changes)
        cfg.validate_features()
    except ValueError as e:
        raise SystemExit(f"error: --set: {e}") from None
    tmp = args.dest.parent / f".{args.dest.name}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    processor_files = {p.name for p in src.glob("policy_*processor*")}
    written_here = {"config.json"} | ({"model.safetensors"} if weights is not None else set())
    try:
        for path in sorted(src.iterdir()):
            if path.is_file() and path.name not in processor_files | written_here:
                shutil.copy(path, tmp / path.name)
        (tmp / "config.json").write_text(json.dumps(raw, indent=4))
        if weights is not None:
            save_file(weights, tmp / "model.safetensors")
        pre, post = make_formation_diffusion_pre_post_processors(cfg, dataset_stats=stats)
        pre.save_pretrained(tmp)
        post.save_pretrained(tmp)
        if all(
            _same_text(src / n, tmp / n) for n in ("policy_preprocessor.json", "policy_postprocessor.json")
        ):
            # The same steps with the same statistics: keep the checkpoint's own files, byte for byte
            # (a rebuilt normalizer stores 1-element statistics with another shape).
            for path in tmp.glob("policy_*processor*"):
                path.unlink()
            for name in sorted(processor_files):
                shutil.copy(src / name, tmp / name)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if args.dest.exists():
        shutil.rmtree(args.dest)
    tmp.rename(args.dest)
    print(
        f"wrote {args.dest} ({', '.join(args.set) or 'no change'}; steps {[type(s).__name__ for s in pre.steps]})"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
