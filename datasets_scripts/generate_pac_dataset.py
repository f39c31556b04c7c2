"""PAC demonstrations as a LeRobot dataset (format v3.0), optionally laid out as a hub dataset repo.

Runs the Path-Aware Controller on seeded valid scenes (all episodes of a batch at once, on the NumPy
core), keeps the successful episodes and writes them with LeRobot's own writer
(``LeRobotDataset.create`` -> ``save_episode`` -> ``finalize``).

Usage::

    lerobot-formation-generate --episodes 1878 --root data/formation_pac          # the paper's size
    lerobot-formation-generate --episodes 10 --root /tmp/tiny --push-to /tmp/hub  # + hub-style folder
    # sharded: each shard is a valid dataset; merge them with LeRobot's own tool
    lerobot-formation-generate --num-shards 2 --shard-index 0 --root data/shard0 &
    lerobot-formation-generate --num-shards 2 --shard-index 1 --root data/shard1 &
    wait
    lerobot-edit-dataset --new_repo_id local/formation_pac --new_root data/merged --operation.type merge \
        --operation.repo_ids "['local/shard0', 'local/shard1']" --operation.roots "['data/shard0', 'data/shard1']"

Features (all float32 with names, fps 10, task string ``TASK``):
- ``observation.state`` (7,): midpoint [x, y, cos phi, sin phi, x', y', omega];
- ``observation.environment_state`` (51,) or (66,): obstacle grid, goal (and obstacle list);
- ``action`` (2,): [v, omega] actually applied (clipped);
- ``scene.seed`` (int64), ``scene.obstacles`` (15,), ``scene.goal`` (2,), ``scene.start`` (3,):
  per-frame scene metadata from which evaluation rebuilds the exact scene of every episode. They are
  not ``observation.*`` keys, so policies ignore them, and as ordinary columns they survive LeRobot's
  split and merge.

Realistic conditions (docs/conditions.md): ``--env.<field> VALUE`` with the env config's names, e.g.
``--env.sensing_range 3 --env.obstacle_noise 0.02``: PAC then drives on what the team perceives, the
frames hold the team's observations and PAC's commands, and ``meta/generation.json`` records them.
``--expert privileged``: PAC acts on the true world instead (every obstacle, moving ones predicted,
the delay compensated) while the frames still hold what the team perceived. ``--conditions-randomize
level5``: each group of 16 seeds gets its own draw of conditions up to level 5's
(``core.perception.conditions.randomized_conditions``)::

    lerobot-formation-generate --episodes 1500 --root data/formation_priv --obstacle-encoding nearest \
        --scene-preset paper,wide,mixed-hard,structures --expert privileged --conditions-randomize level5

Reliability: the dataset is written to a temporary sibling folder ``.NAME.tmp-PID`` and renamed into
place at the end, so an interrupted run leaves nothing at the destination. On any exit (an error,
Ctrl-C, SIGTERM or SIGHUP, which raise SystemExit) the temporary folder is removed and the simulation
workers stopped; after a SIGKILL the workers die with their parent (``pac_episodes._die_with_parent``) and the next
run into the same destination removes the folder (``safe_destination.remove_stale_temporaries``). A run refuses to
start while a live process writes the same destination, checks again right before the rename, and
the rename never replaces a folder that appeared meanwhile (``safe_destination.rename_noreplace``) unless
``--overwrite``. The same arguments give byte-identical data files.

This module is the command line; the jobs live beside it: ``pac_episodes`` (scenes by seed, PAC
simulation in worker processes, shards), ``dataset_frames`` (features and the frames of an
episode), ``lerobot_writer`` (LeRobot's writer, the atomic publish), ``safe_destination``
(temporary folders, the no-replace rename, signals) and ``hub_folder`` (``--push-to``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lerobot_formation.core.encodings.obstacle_grid import ENCODINGS
from lerobot_formation.core.episodes.levels import get_level
from lerobot_formation.core.perception.conditions import Conditions
from lerobot_formation.core.world.presets import SCENE_MIXES, SCENE_PRESETS, distribution_entries
from lerobot_formation.data.hub_folder import hub_destinations, push_to_folder
from lerobot_formation.data.lerobot_writer import generate
from lerobot_formation.data.pac_episodes import EXPERTS
from lerobot_formation.data.safe_destination import (
    check_inside,
    check_replaceable,
    check_repo_id,
    exit_on_signals,
)
from lerobot_formation.envs.condition_flags import add_condition_arguments, conditions_from_flags
from lerobot_formation.threads import add_threads_argument, apply_threads

PAPER_EPISODES = 1878


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        prog="lerobot-formation-generate",
        description="PAC demonstrations as a LeRobot dataset (v3.0).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    ap.add_argument(
        "--episodes", type=int, default=PAPER_EPISODES, help="successful episodes to keep (all shards)"
    )
    ap.add_argument("--seed", type=int, default=0, help="first scene seed")
    ap.add_argument(
        "--repo-id",
        default="local/formation_pac",
        help="dataset id 'owner/name', as LeRobotDataset(repo_id) loads it; also the default --root's name",
    )
    ap.add_argument("--root", default=None, help="dataset folder (default: $HF_LEROBOT_HOME/<repo-id>)")
    ap.add_argument("--scenes", default=None, help="scenes JSON file to use instead of random seeds")
    ap.add_argument(
        "--obstacle-encoding",
        default="grid",
        choices=ENCODINGS,
        help="observation.environment_state: 'grid' (the paper's 7x7 radius grid + goal, 51 values), "
        "'grid+list' (plus the obstacles [x, y, r], 66; the CPU config's) or another encoding of "
        "core/encodings/obstacle_grid.py; must match the policy trained on it",
    )
    ap.add_argument(
        "--scene-slots",
        type=int,
        default=0,
        help="at least this many obstacle rows in scene.obstacles (to merge with a dataset of a wider "
        "preset, e.g. 15 for 'wide'); default: as many as the scenes need",
    )
    ap.add_argument(
        "--scene-preset",
        default="paper",
        help=f"scene distribution: a preset {tuple(SCENE_PRESETS)}, a mixture {tuple(SCENE_MIXES)}, or a "
        "comma list of those, e.g. 'paper,wide,mixed-hard,structures' (seed s draws entry s %% k; "
        "core/world/sampling.py sample_distribution)",
    )
    ap.add_argument(
        "--expert",
        default="pac",
        choices=EXPERTS,
        help="who drives: 'pac' on what the team perceives, or 'privileged': PAC on the true world "
        "(every obstacle, its velocity, moving ones predicted, the action delay compensated) while the "
        "frames hold what the team perceived (docs/conditions.md); 'oracle': the plans of a search on the "
        "true simulator (core/episodes/oracle.py, seconds a scene), the frames what the team perceived; 'policy': the checkpoint at "
        "--policy.path with its safety layer (best-of-10 + CBF, told the conditions), on what the team "
        "perceives (self-imitation; needs --workers 0)",
    )
    ap.add_argument(
        "--policy.path",
        dest="policy_path",
        default=None,
        help="checkpoint folder of --expert policy (only with it)",
    )
    ap.add_argument(
        "--conditions-randomize",
        default=None,
        metavar="LEVEL",
        help="draw each group of 16 seeds' conditions up to this graded level's (level4, level5): each "
        "condition on with probability 0.6 at a random severity (not with --env.* flags)",
    )
    ap.add_argument(
        "--push-to", default=None, help="also lay the dataset out as a hub repo under this folder"
    )
    ap.add_argument(
        "--num-shards", type=int, default=1, help="split --episodes into this many independent datasets"
    )
    ap.add_argument("--shard-index", type=int, default=0, help="which shard to write, 0 .. --num-shards - 1")
    ap.add_argument("--batch-size", type=int, default=256, help="episodes simulated at once")
    ap.add_argument("--workers", type=int, default=1, help="simulation processes beside the writer (0: none)")
    ap.add_argument(
        "--slow-write", action="store_true", help="per-frame add_frame instead of episode buffers"
    )
    ap.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing --root (and --push-to copy) if it is a formation dataset this project "
        "wrote (anything else is refused, nothing deleted); without it an existing one is an error",
    )
    ap.add_argument(
        "--no-progress",
        action="store_true",
        help="no progress bar (there is none either when stderr is not a terminal); the summary "
        "line is always printed",
    )
    add_threads_argument(ap, "CPU threads per process, which the data does not depend on")
    add_condition_arguments(ap)
    args = ap.parse_args(argv)
    if args.episodes < 1:
        ap.error(f"--episodes must be >= 1, got {args.episodes}")
    if args.seed < 0:
        ap.error(f"--seed must be >= 0, got {args.seed}")
    if args.num_shards < 1 or not 0 <= args.shard_index < args.num_shards:
        ap.error(f"need 0 <= --shard-index < --num-shards, got {args.shard_index} and {args.num_shards}")
    if args.workers < 0:
        ap.error(f"--workers must be >= 0, got {args.workers}")
    if args.expert == "policy" and args.policy_path is None:
        ap.error("--expert policy needs --policy.path")
    if args.policy_path is not None and args.expert != "policy":
        ap.error(f"--policy.path is only read by --expert policy, got --expert {args.expert}")
    if args.policy_path is not None and not Path(args.policy_path).is_dir():
        ap.error(f"--policy.path {args.policy_path} is not a folder")
    if args.expert == "policy" and args.workers:
        ap.error(f"--expert policy runs in the generating process: give --workers 0, got {args.workers}")
    if args.batch_size < 1:
        ap.error(f"--batch-size must be >= 1, got {args.batch_size}")
    try:
        check_repo_id(args.repo_id)
    except ValueError as e:
        ap.error(str(e))
    if args.scenes and not Path(args.scenes).is_file():
        ap.error(f"--scenes file {args.scenes} does not exist")
    try:
        conditions = conditions_from_flags(args)
    except ValueError as e:
        ap.error(str(e).replace("conditions: ", "--env."))
    try:
        distribution_entries(args.scene_preset)
    except ValueError as e:
        ap.error(f"--scene-preset: {e}")
    if args.conditions_randomize is not None:
        try:
            randomize_ceiling(args.conditions_randomize)
        except ValueError as e:
            ap.error(f"--conditions-randomize: {e}")
        if conditions.enabled:
            ap.error(f"--conditions-randomize excludes --env.* flags, got {conditions.changed()}")
    return args


def randomize_ceiling(level: str | None) -> Conditions | None:
    """The ceiling of ``--conditions-randomize LEVEL``: that graded level's conditions (None: no
    randomizing); ValueError for an unknown level or one without conditions."""
    if level is None:
        return None
    ceiling = get_level(level).conditions
    if not ceiling.enabled:
        raise ValueError(f"level {level!r} has no conditions to randomize; choose level4 or level5")
    return ceiling


def policy_expert(policy_path: str | None):
    """``--expert policy``'s controllers: the checkpoint's "diffusion-safe" (None without a path)."""
    if policy_path is None:
        return None
    from lerobot_formation.bench.controllers import PolicyExpert

    return PolicyExpert(policy_path)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    apply_threads(args.threads)  # before lerobot loads torch, and inherited by the workers
    from lerobot_formation.plugin import quiet_torchcodec_warning

    quiet_torchcodec_warning()  # LeRobotDataset.create logs torchcodec's FFmpeg traceback otherwise
    if args.root is None:
        from lerobot.utils.constants import HF_LEROBOT_HOME

        args.root = str(check_inside(Path(HF_LEROBOT_HOME) / args.repo_id, Path(HF_LEROBOT_HOME), "--root"))
    with exit_on_signals():
        return _run(args, argv)


def _run(args: argparse.Namespace, argv: list[str] | None) -> int:
    try:
        if args.overwrite:  # refuse before generating, not after
            check_replaceable(Path(args.root))
        if args.push_to:
            hub_destinations(Path(args.push_to), args.repo_id, args.overwrite)
        summary = generate(
            Path(args.root),
            args.repo_id,
            args.episodes,
            seed=args.seed,
            obstacle_encoding=args.obstacle_encoding,
            scenes_path=args.scenes,
            num_shards=args.num_shards,
            shard_index=args.shard_index,
            overwrite=args.overwrite,
            fast_write=not args.slow_write,
            batch_size=args.batch_size,
            progress=not args.no_progress and sys.stderr.isatty(),  # no bars in logs
            workers=args.workers,
            scene_preset=args.scene_preset,
            min_scene_slots=args.scene_slots,
            conditions=conditions_from_flags(args),
            expert=args.expert,
            randomize=randomize_ceiling(args.conditions_randomize),
            policy_expert=policy_expert(args.policy_path),
        )
    except (FileExistsError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.push_to:
        command = "lerobot-formation-generate " + " ".join(sys.argv[1:] if argv is None else argv)
        try:
            dest = push_to_folder(
                Path(args.root), Path(args.push_to), args.repo_id, summary, command, args.overwrite
            )
        except (FileExistsError, ValueError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        summary["pushed_to"] = str(dest)
    if summary["episodes"] < summary["requested_episodes"]:
        print(
            f"warning: only {summary['episodes']} of the {summary['requested_episodes']} episodes asked for: "
            f"{expert_name(summary)} succeeded on {summary['pac_succeeded']} of the {summary['pac_attempted']} "
            f"scenes of {args.scenes}",
            file=sys.stderr,
        )
    print(summary_line(summary, args.root))
    return 0


EXPERT_NAMES = {
    "pac": "PAC",
    "privileged": "the privileged expert",
    "oracle": "the oracle",
    "policy": "the policy with its layer",
}


def expert_name(summary: dict) -> str:
    """Who drove, for messages (the summary's ``pac_*`` counts are the expert's, whichever it is)."""
    return EXPERT_NAMES[summary.get("expert", "pac")]


def summary_line(summary: dict, root: str) -> str:
    """The one-line summary: what was written, and the expert's success over the scenes it ran. It runs
    whole batches of scenes, so it can run more scenes than episodes were asked for; the line says so."""
    ran, ok, kept = summary["pac_attempted"], summary["pac_succeeded"], summary["episodes"]
    pac = f"{expert_name(summary)} succeeded on {ok} of {ran} scenes ({summary['pac_success_rate']:.1%})"
    if ok > kept:
        pac += f"; scenes run in whole batches, the first {kept} successes kept"
    line = f"episodes {kept}, frames {summary['frames']}, {summary['mb']:.1f} MB, {pac}, {summary['seconds']:.1f} s -> {root}"
    if summary.get("pushed_to"):
        line += f"; hub folder -> {summary['pushed_to']}"
    return line


if __name__ == "__main__":
    raise SystemExit(main())
