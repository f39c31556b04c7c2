"""Distil a few-step sampler from a ``formation_diffusion`` checkpoint (direct distillation).

Teacher: the checkpoint's EMA model with its own sampler (DDIM, ``num_inference_steps`` steps, e.g. 10),
which with eta = 0 is a deterministic map x_T -> x_0 of the initial noise and the observation history o
(Song et al. 2021, DDIM eq. 12 with sigma = 0).

Student: a copy of the teacher's U-Net, initialised with its weights, that predicts x_0 directly
(``prediction_type="sample"``) and samples with S DDIM steps spaced "trailing" (the first step at the
last training timestep T - 1, so S = 1 is one U-Net call on pure noise). It is trained to reproduce the
teacher's sample from the same noise (Luhman & Luhman 2021, "Knowledge distillation in iterative
generative models for improved sampling speed", eq. 5):

    L = E_{o ~ dataset, x_T ~ N(0, I)} || x0_student(x_T, o) - x0_teacher(x_T, o) ||^2

over the whole predicted horizon, with x0_student the student's last x_0 prediction (not clipped, so the
gradient reaches it). An EMA of the student's weights (the policy's own ``update``, its warm-up
restarted) is what is saved and evaluated.

The result is an ordinary ``formation_diffusion`` checkpoint (the teacher's config with
``prediction_type="sample"``, ``num_inference_steps=S``, ``timestep_spacing="trailing"``, and the
teacher's processors), so ``lerobot-eval --policy.path``, ``lerobot-formation-bench`` and
``benchmarks/bench_sampling_steps.py --student`` run it as they run any checkpoint.

Run (one CPU thread; resumable: rerun the same command to continue from ``OUT/last``)::

    python -m lerobot_formation.policy.distill --teacher pretrained/formation_diffusion_safe \\
        --dataset.root data/formation_wide_route --student-steps 1 --steps 4000 --out outputs/distill_1step

The dataset must hold the teacher's obstacle encoding (its ``input_features``); another is refused at
start-up. It writes ``OUT/last`` (weights, optimizer and step, every ``--save-every`` steps; a rerun resumes
from it, loading it with ``torch.load(weights_only=True)``: tensors and numbers only, so a planted
pickle is refused, never run) and, at the end,
``OUT/pretrained_model`` (the student checkpoint; written to a temporary folder and renamed into
place), with ``distill_log.json`` (the loss curve) beside it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import shutil
import sys
import time
from pathlib import Path

from lerobot_formation.threads import add_threads_argument, apply_threads

logger = logging.getLogger(__name__)
PROCESSOR_FILES = ("policy_preprocessor", "policy_postprocessor")
CARRIED_FILES = ("dataset_scenes.json",)  # files of the teacher's folder the student keeps


def student_config(teacher_cfg, student_steps: int):
    """The teacher's config for an x_0-predicting student of ``student_steps`` trailing DDIM steps
    (``dataclasses.replace``: the config's checks run). The student samples from pure noise, as it was
    trained: a teacher's warm start is dropped."""
    return dataclasses.replace(
        teacher_cfg,
        noise_scheduler_type="DDIM",
        prediction_type="sample",
        num_inference_steps=int(student_steps),
        timestep_spacing="trailing",
        warm_start_step=0,
    )


def student_sample(model, cond, noise, steps: int):
    """The student's S-step DDIM sample with gradients: (x_0 of the last step unclipped, x_0 clipped).

    ``model.noise_scheduler`` must be the student's (DDIM, trailing, prediction "sample"); the
    intermediate steps are diffusers' ``DDIMScheduler.step`` (differentiable torch operations)."""
    import torch

    scheduler = model.noise_scheduler
    scheduler.set_timesteps(steps)
    sample = noise
    x0 = None
    for i, t in enumerate(scheduler.timesteps):
        t_batch = torch.full(sample.shape[:1], int(t), dtype=torch.long, device=sample.device)
        x0 = model.unet(sample, t_batch, cond)
        if i + 1 < len(scheduler.timesteps):
            sample = scheduler.step(x0, t, sample).prev_sample
    return x0


def _processor_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.name.startswith(PROCESSOR_FILES))


def export_student(policy, teacher_path: Path, dest: Path, log: dict) -> None:
    """Write the student checkpoint (config, weights, the teacher's processors, a card) into ``dest``
    through a temporary folder renamed into place; an existing ``dest`` is replaced."""
    tmp = dest.with_name(f".{dest.name}.tmp-{os.getpid()}")
    if tmp.exists():
        shutil.rmtree(tmp)
    policy.save_pretrained(tmp)
    for f in _processor_files(teacher_path):
        shutil.copy2(f, tmp / f.name)
    for name in CARRIED_FILES:
        if (teacher_path / name).is_file():
            shutil.copy2(teacher_path / name, tmp / name)
    (tmp / "distill_log.json").write_text(json.dumps(log, indent=1))
    cfg = policy.config
    (tmp / "README.md").write_text(
        f"# {dest.name}: a {cfg.num_inference_steps}-step distilled formation_diffusion student\n\n"
        f"Teacher: `{log['teacher']}` ({log['teacher_sampler']}). Direct distillation "
        "(`python -m lerobot_formation.policy.distill`, module docstring): the student predicts x_0 "
        f"(`prediction_type: sample`) with {cfg.num_inference_steps} DDIM step(s) spaced `trailing`, trained "
        f"{log['steps']} steps of batch {log['batch_size']} on observation histories of `{log['dataset_root']}` "
        f"to match the teacher's sample from the same noise. Final loss (mean of the last 100 steps): "
        f"{log['final_loss']:.5f}; wall time {log['wall_s'] / 60:.1f} min on {log['threads']} thread(s).\n\n"
        "Command:\n\n```\n" + log["command"] + "\n```\n"
    )
    old = dest.with_name(f".{dest.name}.old-{os.getpid()}")
    if dest.exists():
        dest.rename(old)
    tmp.rename(dest)
    if old.exists():
        shutil.rmtree(old)


def _save_last(out: Path, policy, optimizer, scheduler, step, losses: list[float], started: float) -> None:
    import torch

    tmp = out / f".last.tmp-{os.getpid()}"
    tmp.mkdir(parents=True, exist_ok=True)
    torch.save(
        {
            "policy": policy.state_dict(),
            "optimizer": optimizer.state_dict(),
            "scheduler": scheduler.state_dict(),
            "step": step,
            "losses": losses,
            "wall_s": time.time() - started,
            "rng": torch.get_rng_state(),
        },
        tmp / "state.pt",
    )
    last = out / "last"
    old = out / f".last.old-{os.getpid()}"
    if last.exists():
        last.rename(old)
    tmp.rename(last)
    if old.exists():
        shutil.rmtree(old)


def main(argv: list[str] | None = None) -> int:
    # A local teacher and dataset: offline unless the caller says otherwise (set here, before LeRobot and
    # huggingface_hub load, never at import).
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
    ap = argparse.ArgumentParser(
        prog="python -m lerobot_formation.policy.distill",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    ap.add_argument("--teacher", required=True, help="formation_diffusion checkpoint folder (the teacher)")
    ap.add_argument(
        "--dataset.root",
        dest="dataset_root",
        default=None,
        help="LeRobot dataset folder whose observations condition the samples (default: the teacher's "
        "train_config.json dataset.root)",
    )
    ap.add_argument("--out", required=True, help="output folder (OUT/last, OUT/pretrained_model)")
    ap.add_argument("--student-steps", type=int, default=1, help="student DDIM steps S (default: 1)")
    ap.add_argument("--steps", type=int, default=4000, help="optimizer steps (default: %(default)s)")
    ap.add_argument(
        "--batch-size", type=int, default=256, help="observations per step (default: %(default)s)"
    )
    ap.add_argument("--lr", type=float, default=1e-4, help="AdamW learning rate (default: %(default)s)")
    ap.add_argument("--save-every", type=int, default=250, help="steps between OUT/last saves")
    ap.add_argument("--seed", type=int, default=0, help="seed of the noise and the data order")
    ap.add_argument("--log-every", type=int, default=50, help="steps between loss lines")
    add_threads_argument(ap, "torch threads")
    args = ap.parse_args(argv)
    for name in ("student_steps", "steps", "batch_size", "save_every", "log_every"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if not args.lr > 0:
        ap.error(f"--lr must be > 0, got {args.lr}")

    import torch
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
    from lerobot.utils.constants import ACTION

    from lerobot_formation.compat.lerobot_compat import global_conditioning
    from lerobot_formation.policy.checkpoint import CheckpointError, load_policy
    from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy

    threads = apply_threads(args.threads)
    teacher_path = Path(args.teacher)
    try:
        teacher, pre, _ = load_policy(teacher_path)
    except CheckpointError as e:
        ap.error(f"--teacher: {e}")
    tcfg = teacher.config
    if tcfg.prediction_type != "epsilon" and tcfg.timestep_spacing == "trailing":
        logger.warning("the teacher is itself a distilled student (%s)", teacher_path)
    train_cfg = teacher_path / "train_config.json"
    trained_on = json.loads(train_cfg.read_text())["dataset"] if train_cfg.is_file() else {}
    root = args.dataset_root or trained_on.get("root")
    if root is None:
        ap.error(f"--dataset.root is needed: {teacher_path} has no train_config.json to take it from")
    if not Path(root).is_dir():
        ap.error(f"--dataset.root {root} does not exist (regenerate it with its command in the README)")
    repo_id = trained_on.get("repo_id") or "local/dataset"

    torch.manual_seed(args.seed)
    # the observation windows only (no action chunks), from the metadata: the dataset is read once
    meta = LeRobotDatasetMetadata(repo_id, root=root)
    for key, feature in tcfg.input_features.items():
        theirs = tuple(meta.features[key]["shape"]) if key in meta.features else None
        if theirs != tuple(feature.shape):
            ap.error(
                f"--dataset.root {root} gives '{key}' shape {theirs}, but the teacher takes {tuple(feature.shape)} "
                f"(its obstacle_encoding is {tcfg.obstacle_encoding!r}): distil on a dataset of that encoding"
            )
    delta = {k: v for k, v in resolve_delta_timestamps(tcfg, meta).items() if k != ACTION}
    dataset = LeRobotDataset(repo_id, root=root, delta_timestamps=delta)
    loader = torch.utils.data.DataLoader(
        dataset,
        batch_size=args.batch_size,
        shuffle=True,
        drop_last=True,
        generator=torch.Generator().manual_seed(args.seed),
    )

    scfg = student_config(tcfg, args.student_steps)
    student = FormationDiffusionPolicy(scfg)
    student.load_state_dict(teacher.state_dict())
    # the student's own schedulers (x_0 prediction, trailing) on the teacher's betas
    from lerobot_formation.policy.checkpoint import set_inference_steps

    set_inference_steps(student, args.student_steps)
    if student.ema_diffusion is not None:
        student.ema_step.zero_()  # restart the EMA warm-up for the student
    optimizer = torch.optim.AdamW(student.diffusion.parameters(), lr=args.lr, weight_decay=1e-6)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=args.steps)
    step, losses, wall_before = 0, [], 0.0
    if (out / "last" / "state.pt").is_file():
        try:  # tensors, numbers, lists and dicts only: a pickled object in the file is refused, never run
            saved = torch.load(out / "last" / "state.pt", weights_only=True)
        except Exception as e:  # noqa: BLE001  (UnpicklingError, a truncated file, ...)
            ap.error(
                f"{out / 'last' / 'state.pt'} is not a distillation state this program wrote (it holds more than "
                f"tensors and numbers, or is damaged: {type(e).__name__}); nothing in it was run. Move it away "
                "to start afresh"
            )
        student.load_state_dict(saved["policy"])
        optimizer.load_state_dict(saved["optimizer"])
        scheduler.load_state_dict(saved["scheduler"])
        scheduler.T_max = args.steps  # a rerun may ask for more steps
        step, losses, wall_before = saved["step"], saved["losses"], saved["wall_s"]
        torch.set_rng_state(saved["rng"])
        print(f"resumed from {out / 'last'} at step {step}", flush=True)

    teacher.eval()
    student.train()
    started = time.time() - wall_before
    device_keys = [k for k in tcfg.input_features]
    horizon, action_dim = tcfg.horizon, tcfg.action_feature.shape[0]
    teacher_sampler = f"DDIM {tcfg.num_inference_steps} steps, {tcfg.timestep_spacing}"
    print(
        f"teacher {teacher_path} ({teacher_sampler}), student {args.student_steps} step(s) trailing, x_0 "
        f"prediction; dataset {root} ({dataset.num_frames} frames); batch {args.batch_size}, lr {args.lr}, "
        f"{args.steps} steps; torch threads {threads}",
        flush=True,
    )
    t_log = time.time()
    while step < args.steps:
        for raw in loader:
            if step >= args.steps:
                break
            batch = pre({k: raw[k] for k in device_keys if k in raw})
            obs = {k: batch[k] for k in device_keys}
            noise = torch.randn(args.batch_size, horizon, action_dim)
            with torch.inference_mode():
                cond_t = global_conditioning(teacher.inference_model, obs)
                target = teacher._sample(teacher.inference_model, cond_t, noise)
            target = target.clone()
            cond = global_conditioning(student.diffusion, obs)
            x0 = student_sample(student.diffusion, cond, noise, args.student_steps)
            loss = torch.nn.functional.mse_loss(x0, target)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(student.diffusion.parameters(), 10.0)
            optimizer.step()
            scheduler.step()
            student.update()
            step += 1
            losses.append(float(loss.detach()))
            if step % args.log_every == 0 or step == args.steps:
                recent = losses[-args.log_every :]
                rate = args.log_every / max(time.time() - t_log, 1e-9)
                t_log = time.time()
                print(
                    f"step {step}/{args.steps} loss {sum(recent) / len(recent):.5f} lr "
                    f"{scheduler.get_last_lr()[0]:.2e} ({rate:.2f} steps/s)",
                    flush=True,
                )
            if step % args.save_every == 0 or step == args.steps:
                _save_last(out, student, optimizer, scheduler, step, losses, started)

    wall = time.time() - started
    log = {
        "teacher": str(teacher_path),
        "teacher_sampler": teacher_sampler,
        "dataset_root": str(root),
        "student_steps": args.student_steps,
        "steps": step,
        "batch_size": args.batch_size,
        "lr": args.lr,
        "seed": args.seed,
        "threads": threads,
        "wall_s": wall,
        "final_loss": sum(losses[-100:]) / max(len(losses[-100:]), 1),
        "losses_every_50": losses[::50],
        "command": "python -m lerobot_formation.policy.distill "
        + " ".join(sys.argv[1:] if argv is None else argv),
        "date": time.strftime("%Y-%m-%d"),
    }
    student.eval()
    export_student(student, teacher_path, out / "pretrained_model", log)
    print(f"wrote {out / 'pretrained_model'} (final loss {log['final_loss']:.5f}, {wall / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
