"""DAgger-style relabelling, step 1: the states a policy visits, as a scenes file for the expert.

Runs a diffusion checkpoint (standard sampling, no safety layer, so it visits its own mistakes) on
seeded scenes of a preset with the batched engine, then picks branch points along its trajectories:
the poses a few steps before each collision (where a correction was needed most) and random poses of
the other episodes. Each branch point becomes a scene (same obstacles and goal, the visited pose as
the start) in a scenes file. Step 2 is the demonstrator labelling those states, i.e. PAC driving on
from each of them, written as a LeRobot dataset by the generator; step 3 merges it with the original
demonstrations and training resumes from the checkpoint::

    python -m datasets_scripts.dagger_scenes --policy.path CKPT --scene-preset wide --rollouts 400 \\
        --out data/dagger_scenes.json
    lerobot-formation-generate --scenes data/dagger_scenes.json --episodes 100000 \\
        --obstacle-encoding nearest --root data/formation_dagger --repo-id local/formation_dagger
    lerobot-edit-dataset --new_repo_id local/formation_wide_dagger --new_root data/formation_wide_dagger \\
        --operation.type merge --operation.repo_ids "['local/formation_wide','local/formation_dagger']" \\
        --operation.roots "['data/formation_wide','data/formation_dagger']"

(``--episodes`` larger than the file: the generator keeps every branch PAC completes.) The policy
observes only the midpoint and the obstacles, so a branch restarts the followers at their usual
offsets from the visited pose; PAC's labels depend on the pose only.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from lerobot_formation.core.dynamics import FormationParams
from lerobot_formation.core.footprint import sequence_clearance
from lerobot_formation.core.rollout import COLLISION, rollout
from lerobot_formation.core.scene import (
    SCENE_PRESETS,
    SceneConfig,
    Scenes,
    passage_exists,
    sample_scenes,
    save_scenes,
    scene_preset,
)
from lerobot_formation.threads import add_threads_argument, apply_threads

DAGGER_SEED_START = 3_000_000  # disjoint from the dataset (0...) and the evaluation seeds (1_000_000...)


def branch_points(
    poses: np.ndarray, steps: np.ndarray, outcome: np.ndarray, rng: np.random.Generator, per_episode: int
) -> list[tuple[int, int]]:
    """(episode, step) pairs: before a collision at 3, 6, 10, 15 ... steps back; otherwise random steps."""
    out = []
    for b in range(len(steps)):
        n = int(steps[b])
        if n < 4:
            continue
        if outcome[b] == COLLISION:
            back = [3, 6, 10, 15, 22, 30][:per_episode]
            out += [(b, n - k) for k in back if n - k > 0]
        else:
            out += [
                (b, int(t))
                for t in rng.choice(np.arange(1, n - 2), size=min(per_episode // 2, n - 3), replace=False)
            ]
    return out


def dagger_scenes(
    policy_path: str,
    preset: str,
    rollouts: int,
    seed: int = DAGGER_SEED_START,
    per_episode: int = 4,
    num_inference_steps: int | None = None,
    min_clearance: float = 0.05,
) -> tuple[Scenes, dict]:
    from lerobot_formation.bench.diffusion_controller import DiffusionController

    params = FormationParams()
    scenes = sample_scenes(seed + np.arange(rollouts), scene_preset(preset))
    ctrl = DiffusionController(policy_path, num_inference_steps=num_inference_steps, seed=seed, params=params)
    rec = rollout(scenes, ctrl, params)
    rng = np.random.default_rng(seed)
    pts = branch_points(rec.poses, rec.steps, rec.outcome, rng, per_episode)
    b = np.array([p[0] for p in pts], dtype=np.int64)
    t = np.array([p[1] for p in pts], dtype=np.int64)
    start = rec.poses[b, t]
    branch = Scenes(scenes.obstacles[b], scenes.mask[b], scenes.goal[b], start, scenes.seeds[b])
    # keep starts whose formation footprint is clear (a state inside an obstacle cannot be relabelled)
    tmpl = np.asarray(params.graph.template)
    clear, _ = sequence_clearance(
        start, np.zeros((len(b), 1, 1, 2)), branch.obstacles, tmpl, params.dt, params.agent_radius
    )
    far = np.linalg.norm(start[:, :2] - branch.goal, axis=-1) > 3 * params.goal_tolerance
    keep = (clear[:, 0] >= min_clearance) & far
    if keep.any():  # and a passage must remain from there (the scenes file's own load-time check)
        idx = np.flatnonzero(keep)
        keep[idx] = passage_exists(branch[idx], SceneConfig())
    branch = branch[np.flatnonzero(keep)]
    summary = {
        "rollouts": rollouts,
        "policy_success": float(np.mean(rec.outcome == 1)),
        "policy_collisions": int(np.sum(rec.outcome == COLLISION)),
        "branch_points": len(pts),
        "kept": int(keep.sum()),
        "preset": preset,
        "seed": seed,
    }
    return branch, summary


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="dagger_scenes",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    ap.add_argument("--policy.path", dest="policy_path", required=True, help="checkpoint folder")
    ap.add_argument("--scene-preset", default="wide", choices=tuple(SCENE_PRESETS), help="scene distribution")
    ap.add_argument("--rollouts", type=int, default=400, help="policy episodes to run")
    ap.add_argument("--seed", type=int, default=DAGGER_SEED_START, help="first scene seed of the rollouts")
    ap.add_argument("--per-episode", type=int, default=4, help="branch points per episode")
    ap.add_argument(
        "--num-inference-steps", type=int, default=None, help="DDIM steps (default: checkpoint's)"
    )
    ap.add_argument("--out", required=True, help="scenes JSON file to write")
    add_threads_argument(ap, "torch threads of the policy")
    args = ap.parse_args(argv)
    apply_threads(args.threads)
    if args.rollouts < 1 or args.per_episode < 1:
        ap.error("--rollouts and --per-episode must be >= 1")
    if not (Path(args.policy_path) / "config.json").is_file():
        print(
            f"error: --policy.path {args.policy_path} is not a checkpoint folder (no config.json)",
            file=sys.stderr,
        )
        return 2
    branch, summary = dagger_scenes(
        args.policy_path,
        args.scene_preset,
        args.rollouts,
        args.seed,
        args.per_episode,
        args.num_inference_steps,
    )
    save_scenes(branch, args.out)
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
