"""Export a training checkpoint as a small hub-style model folder with the EMA weights only.

    python scripts/export_pretrained.py outputs/train_cpu/checkpoints/last/pretrained_model \
        pretrained/formation_diffusion_cpu --dataset.root data/formation_pac_list --card results.md

Writes config.json (use_ema false: the EMA weights are the weights), model.safetensors (the EMA
denoiser stored as ``diffusion.*``), the pre/post-processors, dataset_scenes.json (the first 100
scenes of the training dataset, for the "dataset episodes" protocol without the dataset) and a
model card README.md. Written to a temporary folder, then renamed into place.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("dest", type=Path)
    ap.add_argument("--dataset.root", dest="dataset_root", required=True)
    ap.add_argument(
        "--card", type=Path, default=None, help="markdown with measured results for the model card"
    )
    ap.add_argument("--scenes", type=int, default=100)
    args = ap.parse_args(argv)
    ckpt = args.checkpoint
    if not (ckpt / "model.safetensors").is_file():
        raise SystemExit(f"error: {ckpt} has no model.safetensors")
    if args.dest.exists() and not (args.dest / "dataset_scenes.json").is_file():
        # Only a folder this script wrote (it always holds dataset_scenes.json) is replaced.
        raise SystemExit(
            f"error: {args.dest} exists and is not a model folder written by this script; "
            "choose another destination"
        )
    tmp = args.dest.parent / f".{args.dest.name}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        from safetensors.torch import load_file, save_file  # torch: after the arguments (--help stays quick)

        state = load_file(ckpt / "model.safetensors")
        ema = {k.removeprefix("ema_"): v for k, v in state.items() if k.startswith("ema_diffusion.")}
        if not ema:
            raise SystemExit(f"error: {ckpt} holds no ema_diffusion.* weights")
        save_file({k: v.contiguous() for k, v in ema.items()}, tmp / "model.safetensors")
        cfg = json.loads((ckpt / "config.json").read_text())
        cfg["use_ema"] = False
        (tmp / "config.json").write_text(json.dumps(cfg, indent=4))
        for f in ckpt.iterdir():
            if f.name.startswith("policy_") or f.name == "train_config.json":
                shutil.copy(f, tmp / f.name)
        from lerobot_formation.bench.scene_sets import dataset_scenes
        from lerobot_formation.core.world.scene_files import save_scenes

        save_scenes(dataset_scenes(args.dataset_root, args.scenes), tmp / "dataset_scenes.json")
        card = args.card.read_text() if args.card else ""
        (tmp / "README.md").write_text(card)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = args.dest.parent / f".{args.dest.name}.old"
    if args.dest.exists():
        os.rename(args.dest, old)  # the previous export stays whole until the new one is in place
    os.rename(tmp, args.dest)
    shutil.rmtree(old, ignore_errors=True)
    size = sum(f.stat().st_size for f in args.dest.iterdir()) / 1e6
    print(f"wrote {args.dest} ({size:.1f} MB)")


if __name__ == "__main__":
    main()
