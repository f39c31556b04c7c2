"""``lerobot-formation-bench``: the paper's experiments in one command.

Runs controllers on a scene set with the batched evaluation engine, computes every SPEC metric
(Wilson 95 % intervals on success), and writes ``results.json``, ``tables.md`` (the paper's two
tables with its own numbers beside ours) and PNG figures.

Example::

    lerobot-formation-bench --controllers pac,mppi,diffusion,diffusion-bestof \\
        --policy.path pretrained/formation_diffusion_cpu --scenes dataset:100 --unseen random:100 \\
        --seed 1000000 --out outputs/bench

Scenes: ``random:N`` (the valid scenes of seeds S..S+N-1, S = --seed, default 1_000_000, which the
dataset never uses; ``<preset>:N`` the same from a scene preset of ``core.world.presets.SCENE_PRESETS``, e.g.
``gates:25``; ``hard:N`` N/4 scenes of each of gates, blockers, dense and goals), the
``dataset:N`` (the first N episodes of a dataset: ``--dataset.root``, or the
``dataset_scenes.json`` shipped with the policy), or a scenes JSON file. ``--unseen random:N`` also
runs the diffusion controllers on unseen scenes for the standard-vs-best-of-K table.

Realistic conditions: ``--env.<field> VALUE`` with the env config's field names (docs/conditions.md),
e.g. ``--env.sensing_range 3 --env.action_delay 2 --env.moving_obstacles 2 --env.obstacle_speed 0.3``;
every controller then sees only what the team perceives. ``results.json`` records them in
``meta.conditions``.

Bad input (arguments, scene files, a ``--policy.path`` that is missing, incomplete, broken or of
another policy type, a controller the checkpoint cannot serve) is one line ``error: ...`` on stderr
and exit code 2. If a controller fails after others finished, ``results.json`` and ``tables.md`` are
still written with the finished ones (``meta.incomplete``, ``meta.error``) before the error.
Clearance metrics are null (n/a in the tables) for scenes with no obstacle.

Graded levels: ``--scenes levelK:N`` runs the first N scenes of level K (``lerobot_formation.core.episodes.levels``)
under the level's conditions, from the level's first seed unless ``--seed`` is given. Each scene set
runs under its own conditions: ``--scenes`` and ``--unseen`` a level's if it is a level, else the
``--env`` flags (``scene_sets.scene_set_conditions``; ``--env`` flags with a level are an error);
``results.json`` records them in ``meta.conditions`` and ``meta.unseen_conditions``.

Sharding: ``--shard I/N`` runs the scenes whose index i in the scene set has i % N == I (each keeps
its seed and index); ``lerobot-formation-bench-merge`` (``python -m lerobot_formation.bench.merge``)
combines the N shards' folders into the results.json and tables.md of one run.

``results.json`` and
``tables.md`` are written first (each to a temporary file renamed into place), the figures after
them: a figure that fails is one ``warning:`` line (and ``meta.figure_errors``), the results stay; a
results file that cannot be written (a full disk) is one ``error:`` line, exit code 1, with no
temporary file left behind.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from lerobot_formation.bench.controllers import (
    controller_names,
    controller_summary,
    make_controller,
    needs_policy,
)
from lerobot_formation.bench.evaluation import evaluate
from lerobot_formation.bench.figures import draw_bench_figures
from lerobot_formation.bench.results import (
    collisions_text,
    controller_results,
    existing_run,
    safety_rates,
    write_results,
)
from lerobot_formation.bench.scene_sets import parse_scenes, scene_set_conditions, scene_set_level
from lerobot_formation.bench.settings import RUN_SETTINGS, BenchSettings, ControllerOptions
from lerobot_formation.core.perception.conditions import Conditions
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.core.world.sampling import UNSEEN_SEED_START, SamplingReport
from lerobot_formation.envs.condition_flags import add_condition_arguments, conditions_from_flags
from lerobot_formation.threads import add_threads_argument, apply_threads


class BenchInputError(ValueError):
    """A bad input found while running (a controller that this checkpoint cannot serve, ...): reported
    as one ``error:`` line, exit code 2, after writing the results of the controllers that finished."""


def run_set(
    names,
    scenes,
    params,
    settings: BenchSettings,
    label: str,
    bundle,
    into: dict | None = None,
    records: dict | None = None,
    conditions: Conditions | None = None,
    indices=None,
    jobs: int = 1,
) -> dict:
    """Run the controllers ``names`` on ``scenes`` under ``conditions``; each finished controller's
    entry is put into ``into`` (default: a new dict, returned) at once, so a later failure keeps it.
    ``records``: a dict that also receives each controller's ``EpisodeRecords`` (for the figures, drawn
    after the results are written: ``bench_figures.draw_bench_figures``). ``indices``: each scene's
    index in its whole scene set (a shard's), default 0..len-1. ``jobs`` > 1: controllers run at the
    same time in that many forked processes (the same numbers as one after another)."""
    results = into if into is not None else {}
    spec = (settings.unseen if label == "unseen" else settings.scenes) or ""
    # the controllers know this set's conditions (the unseen set has its own) and whether its obstacles move
    moving = scenes.velocities is not None and bool(np.any(scenes.velocities))
    options = dataclasses.replace(settings.options, conditions=conditions, scenes_move=moving)
    work = (
        scenes,
        params,
        options,
        bundle,
        settings.progress,
        label,
        spec,
        conditions,
        indices,
        records is not None,
    )
    if jobs > 1 and len(names) > 1:
        finished = _run_in_processes(names, work, jobs)
    else:
        finished = (_run_controller(name, work) for name in names)
    for name, entry, rec in finished:
        if records is not None:
            records[name] = rec
        results[name] = entry
    for name in [n for n in names if n in results]:  # the order asked for, whatever finished first
        results[name] = results.pop(name)
    return results


def _run_controller(name: str, work: tuple) -> tuple[str, dict, object]:
    """(name, results entry, episode records or None) of one controller on one scene set; prints its line."""
    scenes, params, options, bundle, progress, label, spec, conditions, indices, keep = work
    t0 = time.perf_counter()
    try:
        ctrl = make_controller(name, params, options, bundle)
    except ValueError as e:
        raise BenchInputError(f"controller {name}: {e}") from e
    rec = evaluate(ctrl, scenes, params, progress=progress, desc=f"{name} ({label})", conditions=conditions)
    entry = controller_results(rec, scenes, indices)
    entry["wall_time_s"] = time.perf_counter() - t0
    notes = getattr(
        ctrl, "episode_notes", None
    )  # what a controller says of each episode (the oracle's causes)
    if notes is not None:
        for episode, note in zip(entry["episodes"], notes(), strict=True):
            episode.update(note)
    if getattr(ctrl, "stats", None):  # the safety layer's interventions
        entry["safety"] = {**ctrl.stats, **safety_rates(ctrl.stats)}
    entry["scenes"] = label
    entry["figures"] = []
    lo, hi = entry["success_ci95"]
    print(  # the set by its spec (random:50, hard:20, dataset:100): "unseen" is not what it is
        f"[{spec or label}] {name}: success {entry['success_rate']:.1%} [{lo:.0%}, {hi:.0%}] of {entry['n_episodes']} "
        f"({collisions_text(entry)}, timeouts {entry['timeouts']}) in {entry['wall_time_s']:.1f} s",
        flush=True,
    )
    return name, entry, rec if keep else None


def cost_rank(name: str) -> int:
    """A rough order of a controller's CPU time per scene, to start the longest first with --jobs:
    K samples per replan (best-of-K, the safety layer) above one sample or MPPI above the rest."""
    if name.endswith(("-safe", "-bestof")):
        return 2
    return 1 if name == "mppi" or needs_policy(name) else 0


_WORK: tuple | None = None  # what the forked workers of _run_in_processes run on (inherited, not pickled)


def _run_in_work(name: str) -> tuple[str, dict, object]:
    return _run_controller(name, _WORK)


def _run_in_processes(names, work: tuple, jobs: int):
    """Yield each controller's (name, entry, records) as it finishes, from ``jobs`` forked processes
    (each controller whole in one process, the costliest started first), so every number is what a
    run with --jobs 1 gives: a controller's episodes, noise streams and batches do not depend on it."""
    import multiprocessing

    global _WORK
    _WORK = work
    order = sorted(names, key=cost_rank, reverse=True)
    context = multiprocessing.get_context("fork")  # the loaded policy and scenes are inherited
    try:
        with context.Pool(min(jobs, len(order))) as pool:
            yield from pool.imap_unordered(_run_in_work, order, chunksize=1)
    finally:
        _WORK = None


DESCRIPTION = """\
Run controllers on a scene set with the batched evaluation engine, and write results.json,
tables.md and figures into --out (docs/benchmark.md)."""
EXAMPLES = """\
examples:
  lerobot-formation-bench --controllers pac,mppi,route-pursuit --scenes random:100 --out outputs/baselines
  lerobot-formation-bench --controllers diffusion,diffusion-safe --policy.path CHECKPOINT \\
      --scenes level5:500 --out outputs/level5
  lerobot-formation-bench --controllers pac,route-pursuit --scenes level5:500 --shard 0/4 \\
      --out outputs/level5_0   (shard 0 of 4; lerobot-formation-bench-merge joins the 4 folders)
  lerobot-formation-bench --controllers diffusion,diffusion-safe --policy.path CHECKPOINT \\
      --scenes level5:500 --out outputs/level5 --resume   (finish a run that stopped)

CHECKPOINT is a formation_diffusion checkpoint folder (the repository's pretrained/ holds the default).
"""
# the settings a resumed run must share with the run in the folder (meta entries of results.json)
RESUME_SETTINGS = (*RUN_SETTINGS, "shard", "seed_policy")


def _controller_lines() -> str:
    """One line per registered controller (``controllers.CONTROLLER_FACTORIES``), in registry order,
    those that read a checkpoint in a second list."""
    names = controller_names()
    width = max(len(n) for n in names) + 2
    lines = ["controllers (--controllers, comma-separated):"]
    lines += [f"  {n:<{width}}{controller_summary(n)}" for n in names if not needs_policy(n)]
    lines.append("controllers that need --policy.path:")
    lines += [f"  {n:<{width}}{controller_summary(n)}" for n in names if needs_policy(n)]
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="lerobot-formation-bench",
        description=DESCRIPTION,
        epilog=f"{EXAMPLES}\n{_controller_lines()}\n",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    scenes = ap.add_argument_group("scenes")
    scenes.add_argument(
        "--scenes",
        default="random:20",
        help="random:N, <preset>:N (paper, wide, gates, blockers, dense, goals, bend, trap, crowd, long, "
        "behind), hard:N, structures:N, mixed-hard:N, levelK:N (K = 0..5, under the level's "
        "conditions), dataset:N or FILE.json (default: %(default)s)",
    )
    scenes.add_argument(
        "--unseen",
        default=None,
        metavar="SCENES",
        help="also run the diffusion controllers on these scenes (random:N; levelK:N under its conditions)",
    )
    scenes.add_argument(
        "--seed",
        type=int,
        default=None,
        help=f"first seed of the scene sets (default: {UNSEEN_SEED_START}, which no dataset uses; a "
        "level's own for levelK:N)",
    )
    scenes.add_argument(
        "--shard",
        default=None,
        metavar="I/N",
        help="run only the scenes whose index i has i %% N == I (merge with lerobot-formation-bench-merge)",
    )
    scenes.add_argument(
        "--dataset.root", dest="dataset_root", default=None, metavar="DIR", help="the dataset of dataset:N"
    )
    controllers = ap.add_argument_group("controllers")
    controllers.add_argument(
        "--controllers",
        default="pac",
        help="comma-separated names, listed below (default: %(default)s)",
    )
    policy = ap.add_argument_group("policy (the controllers that need --policy.path)")
    policy.add_argument(
        "--policy.path",
        dest="policy_path",
        default=None,
        metavar="DIR",
        help="formation_diffusion checkpoint folder",
    )
    policy.add_argument(
        "--candidates",
        type=int,
        default=10,
        metavar="K",
        help="samples per replan of the best-of-K controllers (diffusion-bestof, diffusion-safe, "
        "route-pursuit-safe) (default: %(default)s)",
    )
    policy.add_argument(
        "--num-inference-steps",
        type=int,
        default=None,
        metavar="N",
        help="DDIM denoising steps (default: the checkpoint's)",
    )
    policy.add_argument(
        "--seed-policy",
        type=int,
        default=0,
        metavar="SEED",
        help="seed of the controllers' noise (diffusion, MPPI) (default: %(default)s)",
    )
    add_condition_arguments(
        ap,
        "conditions (docs/conditions.md): all off by default; a level (levelK:N) fixes its own",
    )
    output = ap.add_argument_group("output")
    output.add_argument(
        "--out",
        default="outputs/bench",
        metavar="DIR",
        help="output folder; one that holds another run is refused unless --overwrite or --resume "
        "(default: %(default)s)",
    )
    output.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the run in --out (its results.json and tables.md; figures of the same name are redrawn)",
    )
    output.add_argument(
        "--resume",
        action="store_true",
        help="finish the run in --out: the controllers it finished are kept, not rerun (the same "
        "scenes, seeds, policy and conditions are required)",
    )
    output.add_argument("--no-figures", action="store_true", help="write results.json and tables.md only")
    output.add_argument(
        "--no-progress",
        action="store_true",
        help="no progress bars (there are none either when stderr is not a terminal); the summary "
        "lines are always printed",
    )
    speed = ap.add_argument_group("speed")
    speed.add_argument(
        "--device",
        default="cpu",
        help="torch device of the diffusion controllers' networks: cpu, cuda or cuda:N; scenes, "
        "replanning state and the safety layer stay on the CPU, and the noise is drawn there, so a "
        "seed gives the same initial noise on any device (default: %(default)s)",
    )
    add_threads_argument(speed, "torch threads of the diffusion controllers")
    speed.add_argument(
        "--jobs",
        type=int,
        default=1,
        metavar="N",
        help="run up to N controllers at the same time, each in its own process with --threads threads "
        "(the same numbers as --jobs 1; N x --threads should not exceed the cores) (default: %(default)s)",
    )
    return ap


def _fail(message: str):
    """One line ``error: ...`` on stderr and exit code 2 (bad input; no traceback)."""
    print(f"error: {message}", file=sys.stderr)
    raise SystemExit(2)


def check_device(text: str) -> None:
    """ValueError naming ``text`` unless it is a torch device this machine has (``cpu``, or a CUDA
    device when CUDA is available and the index exists)."""
    import torch

    try:
        device = torch.device(text)
    except (RuntimeError, ValueError):
        raise ValueError(
            f"--device must be a torch device such as cpu, cuda or cuda:0, got {text!r}"
        ) from None
    if device.type == "cpu":
        return
    if device.type != "cuda":
        raise ValueError(f"--device must be cpu or a CUDA device (cuda, cuda:N), got {text!r}")
    if not torch.cuda.is_available():
        raise ValueError(f"--device {text}: CUDA is not available on this machine (use --device cpu)")
    if device.index is not None and device.index >= torch.cuda.device_count():
        raise ValueError(
            f"--device {text}: this machine has {torch.cuda.device_count()} CUDA device(s), no index {device.index}"
        )


def parse_shard(text: str | None) -> tuple[int, int] | None:
    """``"I/N"`` -> (I, N) with 0 <= I < N; None -> None; ValueError naming the value otherwise."""
    if text is None:
        return None
    index, _, count = text.partition("/")
    try:
        i, n = int(index), int(count)
    except ValueError:
        i, n = -1, 0
    if not 0 <= i < n:
        raise ValueError(f"--shard must be I/N with 0 <= I < N (e.g. 0/4), got {text!r}")
    return i, n


def _normalized(value):
    """``value`` as results.json stores it (tuples as lists, ...), to compare with what it holds."""
    return json.loads(json.dumps(value, default=str))


def earlier_results(out: Path, settings: dict) -> dict[str, dict]:
    """The finished controllers' results, by scene set, of the run in ``out`` (its results.json's
    ``by_scenes``; empty when there is none), after checking that it was run with ``settings`` (the
    ``RESUME_SETTINGS`` of this run, a missing one not checked). ValueError naming the file and the
    value that differs."""
    path = out / "results.json"
    if not path.is_file():
        return {}
    try:
        payload = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise ValueError(f"--resume: {path} cannot be read as JSON: {e}") from None
    meta = payload.get("meta") if isinstance(payload, dict) else None
    by_scenes = payload.get("by_scenes") if isinstance(payload, dict) else None
    if not isinstance(meta, dict) or not isinstance(by_scenes, dict):
        raise ValueError(
            f"--resume: {path} is not a lerobot-formation-bench results.json (no meta or by_scenes)"
        )
    for key, value in settings.items():
        if key in meta and meta[key] != _normalized(value):
            raise ValueError(
                f"--resume: the run in {out} has {key} = {meta[key]!r}, this command {_normalized(value)!r}; "
                "resume it with its own settings, or use --overwrite or another --out"
            )
    return {k: dict(v) for k, v in by_scenes.items() if isinstance(v, dict)}


def _write_or_fail(out: Path, results: dict, label: str, settings: BenchSettings, report, **kw) -> None:
    """``write_results``; a file that cannot be written (a full disk, no permission) is one line
    ``error: ...`` and exit code 1."""
    try:
        write_results(out, results, label, settings, report, **kw)
    except OSError as e:
        print(f"error: cannot write the results into {out}: {e}", file=sys.stderr)
        raise SystemExit(1) from e


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    if args.jobs < 1:
        _fail(f"--jobs must be >= 1, got {args.jobs}")
    try:
        shard = parse_shard(args.shard)
        level = scene_set_level(args.scenes)
    except ValueError as e:
        _fail(str(e))
    if args.seed is None:  # resolved here, so results.json records the seed used
        args.seed = level.seed if level is not None else UNSEEN_SEED_START
    apply_threads(args.threads)
    names = [c.strip() for c in args.controllers.split(",") if c.strip()]
    for n in names:
        if n not in controller_names():
            _fail(f"unknown controller {n!r}; choose from {controller_names()}")
    diffusion = [n for n in names if needs_policy(n)]
    if diffusion and not args.policy_path:
        _fail(f"controllers {diffusion} need --policy.path")
    if diffusion:
        try:
            check_device(args.device)
        except ValueError as e:
            _fail(str(e))
    if args.candidates < 1:
        _fail(f"--candidates must be >= 1, got {args.candidates}")
    if args.num_inference_steps is not None and args.num_inference_steps < 1:
        _fail(f"--num-inference-steps must be >= 1, got {args.num_inference_steps}")
    try:
        flags = conditions_from_flags(args)
    except ValueError as e:
        _fail(str(e).replace("conditions: ", "--env."))
    try:  # each set its own: a level's conditions, else the --env flags
        conditions = scene_set_conditions(args.scenes, flags)
        unseen_conditions = scene_set_conditions(args.unseen, flags) if args.unseen else Conditions()
    except ValueError as e:
        _fail(str(e))
    recorded = {"conditions": conditions.changed(), "unseen_conditions": unseen_conditions.changed()}
    out = Path(args.out)
    if args.resume and args.overwrite:
        _fail(
            "--resume keeps the finished controllers of the run in --out, --overwrite replaces it: give one"
        )
    if out.exists() and not out.is_dir():
        _fail(f"--out {out} is a file, not a folder")
    held = existing_run(out)
    if held and not (args.overwrite or args.resume):
        _fail(
            f"--out {out} already holds a run ({held}); add --overwrite to replace it, --resume to finish "
            "it, or choose another folder"
        )
    kept: dict[str, dict] = {}
    if args.resume:
        this_run = {
            "scenes": args.scenes,
            "unseen": args.unseen,
            "seed": args.seed,
            "policy_path": args.policy_path,
            "candidates": args.candidates,
            "num_inference_steps": args.num_inference_steps,
            "shard": args.shard,
            "seed_policy": args.seed_policy,
            **recorded,
        }
        try:
            kept = earlier_results(out, {k: this_run[k] for k in RESUME_SETTINGS})
        except ValueError as e:
            _fail(str(e))
    report = SamplingReport()
    try:
        scenes = parse_scenes(args.scenes, args.seed, args.dataset_root, args.policy_path, report)
        unseen = parse_scenes(args.unseen, args.seed) if args.unseen else None
    except ValueError as e:
        _fail(str(e))
    indices = unseen_indices = None
    if shard is not None:  # a deterministic slice; each scene keeps its seed and its index in the set
        indices = np.arange(shard[0], len(scenes), shard[1])
        scenes = scenes[indices]
        if unseen is not None:
            unseen_indices = np.arange(shard[0], len(unseen), shard[1])
            unseen = unseen[unseen_indices]
        for spec, idx in ((args.scenes, indices), (args.unseen, unseen_indices)):
            if idx is not None and len(idx) == 0:
                _fail(f"--shard {args.shard}: the scene set {spec} has no scene of this shard")
    params = FormationParams()
    label = args.scenes.split(":")[0] if ":" in args.scenes else Path(args.scenes).stem
    # --resume: what the run in --out finished is kept as it is; only the rest runs
    results: dict[str, dict] = {label: dict(kept.get(label, {}))}
    for key, entries in kept.items():
        results.setdefault(key, entries)
    resumed = {key: list(entries) for key, entries in results.items() if entries}
    todo = [n for n in names if n not in results[label]]
    todo_unseen = [n for n in diffusion if n not in results.get("unseen", {})] if unseen is not None else []
    if args.resume:
        finished = ", ".join(f"{c} ({k})" for k, v in resumed.items() for c in v)
        if not resumed:
            print(f"resume: no finished controller in {out}; running them all", flush=True)
        elif not todo and not todo_unseen:
            print(f"resume: nothing to run, every controller asked for has finished in {out}: {finished}")
            return 0
        else:
            print(f"resume: kept from {out / 'results.json'}: {finished}", flush=True)
    bundle = None
    if any(needs_policy(n) for n in (*todo, *todo_unseen)):
        from lerobot_formation.policy.checkpoint import load_policy

        # torch's thread count is --threads (apply_threads set OMP_NUM_THREADS before torch loads).
        try:
            bundle = load_policy(args.policy_path, args.device)
        except ValueError as e:  # CheckpointError: missing, incomplete, broken or another policy type
            _fail(f"--policy.path: {e}")
        steps, most = args.num_inference_steps, bundle[0].config.num_train_timesteps
        if steps is not None and steps > most:
            _fail(
                f"--num-inference-steps must be in [1, {most}] (the checkpoint's training steps), got {steps}"
            )
    out.mkdir(parents=True, exist_ok=True)
    settings = BenchSettings(
        scenes=args.scenes,
        unseen=args.unseen,
        seed=args.seed,
        options=ControllerOptions(
            policy_path=args.policy_path,
            candidates=args.candidates,
            num_inference_steps=args.num_inference_steps,
            seed_policy=args.seed_policy,
            conditions=conditions,
            device=args.device,
        ),
        # progress bars only on a terminal (tqdm writes to stderr), so logs stay free of them
        progress=not args.no_progress and sys.stderr.isatty(),
        order=controller_names(),
        policy_controllers=tuple(n for n in controller_names() if needs_policy(n)),
        shard=args.shard,
    )
    # each controller's episode records, for the figures drawn after the results are written
    records: dict[str, dict] | None = None if args.no_figures else {label: {}, "unseen": {}}
    recorded["resumed"] = resumed
    try:
        into = None if records is None else records[label]
        run_set(
            todo,
            scenes,
            params,
            settings,
            label,
            bundle,
            results[label],
            into,
            conditions,
            indices,
            args.jobs,
        )
        if unseen is not None and diffusion:
            results.setdefault("unseen", {})
            into = None if records is None else records["unseen"]
            run_set(
                todo_unseen,
                unseen,
                params,
                settings,
                "unseen",
                bundle,
                results["unseen"],
                into,
                unseen_conditions,
                unseen_indices,
                args.jobs,
            )
    except BaseException as e:  # keep what finished, then report: one line for bad input, else the traceback
        done = [f"{k}/{c}" for k, v in results.items() for c in v]
        message = str(e) if isinstance(e, BenchInputError) else f"{type(e).__name__}: {e}"
        if done:
            _write_or_fail(out, results, label, settings, report, error=message, **recorded)
            print(f"wrote {out / 'results.json'} with the finished controllers {done}", file=sys.stderr)
        if isinstance(e, BenchInputError):
            _fail(message)
        raise
    if report.drawn:
        print(
            f"scenes: {report.accepted} valid of {report.drawn} drawn, rejection rate {report.rejection_rate:.1%} "
            f"(start covered {report.rejected_start}, obstacle near goal {report.rejected_goal}, "
            f"no passage {report.rejected_passage})"
        )
    _write_or_fail(out, results, label, settings, report, **recorded)  # the results first, the figures after
    print(f"wrote {out / 'results.json'}, {out / 'tables.md'}", flush=True)
    if records is not None:
        specs = {label: args.scenes, "unseen": args.unseen or ""}
        scene_sets = {label: scenes, "unseen": unseen}
        figures, failed = draw_bench_figures(out, results, records, scene_sets, specs, args.seed)
        _write_or_fail(
            out, results, label, settings, report, figure_errors=failed, **recorded
        )  # with the figures' names
        print(f"figures in {out}: {', '.join(figures)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
