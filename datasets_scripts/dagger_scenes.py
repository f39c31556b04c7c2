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
    lerobot-formation-generate --scenes data/dagger_scenes.json --episodes 587 \\
        --obstacle-encoding nearest --root data/formation_dagger --repo-id local/formation_dagger
    lerobot-edit-dataset --new_repo_id local/formation_wide_dagger --new_root data/formation_wide_dagger \\
        --operation.type merge --operation.repo_ids "['local/formation_wide','local/formation_dagger']" \\
        --operation.roots "['data/formation_wide','data/formation_dagger']"

(``--episodes``: the file's scene count, printed as ``kept``; the generator then keeps every branch the
expert completes and stops at the file's end. More than the file holds is an error.) The policy
observes only the midpoint and the obstacles, so a branch restarts the followers at their usual
offsets from the visited pose; PAC's labels depend on the pose only.

Under realistic conditions (docs/conditions.md): ``--level level5`` runs the policy on the level's
scenes under its conditions, ``--env.<field> VALUE`` sets (or overrides) single conditions. A branch
scene then holds the obstacles where they were at the branch point, moving ones with their velocity
then (``"velocities"``, estimated from the step after; they move on when relabelled); what the team
had sensed so far is not kept (the relabelled episode senses afresh). Label the branches under the
same conditions with the privileged expert::

    python -m datasets_scripts.dagger_scenes --policy.path CKPT --level level5 --rollouts 400 \
        --out data/dagger_l5.json
    lerobot-formation-generate --scenes data/dagger_l5.json --episodes 751 --expert privileged \
        --obstacle-encoding nearest --root data/formation_dagger_l5 --repo-id local/formation_dagger_l5 \
        --env.sensing_range 3 --env.obstacle_noise 0.05 --env.pose_noise 0.05 --env.action_noise 0.05 \
        --env.action_delay 1 --env.max_linear_accel 0.5 --env.max_angular_accel 2.0
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np

from lerobot_formation.core.controllers.footprint import TeamBody, sequence_clearance
from lerobot_formation.core.episodes.levels import get_level
from lerobot_formation.core.episodes.rollout import COLLISION, rollout
from lerobot_formation.core.perception.conditions import CONDITION_FIELDS, Conditions
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.core.world.presets import SCENE_MIXES, SCENE_PRESETS, SceneConfig, distribution_entries
from lerobot_formation.core.world.sampling import sample_distribution
from lerobot_formation.core.world.scene_files import save_scenes
from lerobot_formation.core.world.scenes import Scenes
from lerobot_formation.core.world.validity import passage_exists
from lerobot_formation.envs.condition_flags import add_condition_arguments
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
    conditions: Conditions | None = None,
) -> tuple[Scenes, dict]:
    """Branch scenes of ``rollouts`` policy episodes on scenes of ``preset`` (a
    ``core.world.sampling.sample_distribution`` spec) under ``conditions`` (None: none), and a summary."""
    from lerobot_formation.bench.diffusion_controller import DiffusionController

    params = FormationParams()
    scenes = sample_distribution(seed + np.arange(rollouts), preset)
    ctrl = DiffusionController(policy_path, num_inference_steps=num_inference_steps, seed=seed, params=params)
    rec = rollout(scenes, ctrl, params, conditions=conditions)
    rng = np.random.default_rng(seed)
    pts = branch_points(rec.poses, rec.steps, rec.outcome, rng, per_episode)
    b = np.array([p[0] for p in pts], dtype=np.int64)
    t = np.array([p[1] for p in pts], dtype=np.int64)
    start = rec.poses[b, t]
    obstacles, velocities = branch_obstacles(scenes, rec.obstacle_paths, b, t, params.dt)
    branch = Scenes(obstacles, scenes.mask[b], scenes.goal[b], start, scenes.seeds[b], velocities)
    # keep starts whose formation footprint is clear (a state inside an obstacle cannot be relabelled)
    clear, _ = sequence_clearance(start, np.zeros((len(b), 1, 1, 2)), branch.obstacles, TeamBody.of(params))
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
    if conditions is not None and conditions.enabled:
        summary["conditions"] = conditions.changed()
    return branch, summary


def branch_obstacles(
    scenes: Scenes, paths: np.ndarray | None, b: np.ndarray, t: np.ndarray, dt: float
) -> tuple[np.ndarray, np.ndarray | None]:
    """The obstacles (K, M, 3) of the branch points (episode ``b``, step ``t``) where they were at
    that step (``EpisodeRecords.obstacle_paths`` (B, T+1, M, 2); None: static, the scenes' own), and
    their velocities (K, M, 2) over the step after (None when none moves)."""
    obstacles = scenes.obstacles[b].copy()
    if paths is None:
        return obstacles, None
    now = paths[b, t]
    after = paths[b, np.minimum(t + 1, paths.shape[1] - 1)]
    velocities = np.where(np.isfinite(after), (after - now) / dt, 0.0)
    velocities[~scenes.mask[b]] = 0.0
    obstacles[..., :2] = np.where(scenes.mask[b][..., None], now, obstacles[..., :2])
    if not np.any(velocities):
        return obstacles, None
    return obstacles, velocities


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="dagger_scenes",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    ap.add_argument("--policy.path", dest="policy_path", required=True, help="checkpoint folder")
    ap.add_argument(
        "--scene-preset",
        default=None,
        help=f"scene distribution: a preset {tuple(SCENE_PRESETS)}, a mixture {tuple(SCENE_MIXES)} or a "
        "comma list (default: the --level's scenes, else wide)",
    )
    ap.add_argument(
        "--level",
        default=None,
        help="a graded level (level0 .. level5): its scenes and conditions (--env.* flags override single fields)",
    )
    ap.add_argument("--rollouts", type=int, default=400, help="policy episodes to run")
    ap.add_argument("--seed", type=int, default=DAGGER_SEED_START, help="first scene seed of the rollouts")
    ap.add_argument("--per-episode", type=int, default=4, help="branch points per episode")
    ap.add_argument(
        "--num-inference-steps", type=int, default=None, help="DDIM steps (default: checkpoint's)"
    )
    ap.add_argument("--out", required=True, help="scenes JSON file to write")
    add_threads_argument(ap, "torch threads of the policy")
    add_condition_arguments(ap)
    args = ap.parse_args(argv)
    apply_threads(args.threads)
    if args.rollouts < 1 or args.per_episode < 1:
        ap.error("--rollouts and --per-episode must be >= 1")
    try:
        given = {
            f: getattr(args, f"env_{f}") for f in CONDITION_FIELDS if getattr(args, f"env_{f}") is not None
        }
        preset, conditions = rollout_setting(args.level, args.scene_preset, given)
    except ValueError as e:
        ap.error(str(e))
    if not (Path(args.policy_path) / "config.json").is_file():
        print(
            f"error: --policy.path {args.policy_path} is not a checkpoint folder (no config.json)",
            file=sys.stderr,
        )
        return 2
    branch, summary = dagger_scenes(
        args.policy_path,
        preset,
        args.rollouts,
        args.seed,
        args.per_episode,
        args.num_inference_steps,
        conditions=conditions,
    )
    save_scenes(branch, args.out)
    print(json.dumps(summary))
    return 0


def rollout_setting(level: str | None, preset: str | None, given: dict) -> tuple[str, Conditions]:
    """The scene distribution and conditions of the rollouts: the ``level``'s scenes and conditions
    (None: ``wide`` and none), the ``preset`` if given, and the conditions ``given`` by name (the
    ``--env.<field>`` flags) over the level's; ValueError naming a bad level, preset or field."""
    base, scenes = Conditions(), "wide"
    if level is not None:
        lv = get_level(level)
        base, scenes = lv.conditions, ("paper" if lv.scenes == "random" else lv.scenes)
    preset = scenes if preset is None else preset
    distribution_entries(preset)
    return preset, Conditions(**{**asdict(base), **given})


if __name__ == "__main__":
    raise SystemExit(main())
