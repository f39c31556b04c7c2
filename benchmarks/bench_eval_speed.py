"""Evaluation speed (issue 5, benchmark 1): the batched engine against the stock ``lerobot-eval``.

Both evaluate the same checkpoint (``--policy.path``) on the same scenes:

- **engine**: ``evaluate(DiffusionController(path), scenes)``, in this process: every episode at once,
  one batched policy call per replan for the live episodes.
- **stock**: the real ``lerobot-eval`` console script, in a subprocess, with ``--env.type=formation
  --env.scenes_file=<the scenes> --seed=0`` (eval seed i is scene i), once per setting of
  ``--stock``: ``default`` (no ``--eval.*`` flag but the episode count: LeRobot picks
  ``batch_size = min(floor(0.7 x CPUs), n_episodes, 64)``, 1 on 2 cores, hence a sync env) and
  ``B:sync`` / ``B:async`` (``--eval.batch_size=B --eval.use_async_envs=false|true``). lerobot-eval
  always renders 10 episodes to video; that is part of its cost, no flag turns it off.

Timings: the stock ``eval_s`` is lerobot-eval's own timer around ``eval_policy_all`` (rollouts,
rendering, videos; not the Python start-up, imports, env or policy creation); the engine's is
``evaluate()`` alone (the policy loaded before, cold otherwise). The whole-command times (the
subprocess's wall time; the engine's policy load + evaluate) are printed too. Each setting's success
rate is printed, as a check that every run did the same job.

Run (full size, ~1 h with every stock setting at 100 episodes of the default policy)::

    HF_HUB_OFFLINE=1 OMP_NUM_THREADS=1 python benchmarks/bench_eval_speed.py \\
        --policy.path pretrained/<name> --episodes 100

**The safety layer** (``--candidates K``, ``--safety-filter none|cbf``): both paths run the policy's own
best-of-K and filter (config fields ``num_candidates`` / ``safety_filter``): the engine as the bench's
``diffusion-bestof`` / ``diffusion-safe`` controllers, the stock run with ``--policy.num_candidates=K
--policy.safety_filter=...``, always given: the checkpoint's own (the shipped one's K = 10 and CBF
filter) are not the benchmark's. With K = 1 and no filter (the defaults) both run the checkpoint's
sampler alone.
The two success rates are compared with a pooled two-proportion z-test (``within noise``: |z| < 1.96).

**A graded level** (``--level levelK``): both paths play the level's first ``--episodes`` scenes under
its conditions, the engine as the bench's ``--scenes levelK:N`` and the stock run as ``lerobot-eval
--env.level=K --seed=<the level's first seed>`` (docs/benchmark.md). With a safety layer both are told
the level's actuator and moving obstacles (``bench.controllers.safety_settings``; the stock run as
``--policy.safety_world.*`` flags)::

    python benchmarks/bench_eval_speed.py --policy.path pretrained/formation_diffusion_route_v1 \
        --level level5 --episodes 200 --stock 50:sync --threads 1

``--quick`` is a smoke run (10 episodes of 60 steps, three stock settings). The last line is the
ratio of the best stock time to the engine's.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")

import numpy as np  # noqa: E402

from lerobot_formation.threads import add_threads_argument, apply_threads  # noqa: E402

BIN = Path(sys.executable).parent
DEFAULT_STOCK = "default,10:sync,25:sync,50:sync,100:sync,2:async,10:async,25:async"
QUICK_STOCK = "default,10:sync,2:async"


def checkpoint_encoding(path: str) -> str:
    """The env's obstacle encoding that matches the checkpoint's environment_state size."""
    from lerobot_formation.core.encodings.obstacle_grid import ENCODINGS, environment_state_dim

    cfg = json.loads((Path(path) / "config.json").read_text())
    dim = cfg["input_features"]["observation.environment_state"]["shape"][0]
    for e in ENCODINGS:
        if environment_state_dim(e) == dim:
            return e
    raise ValueError(f"{path}: environment_state has {dim} values; no known encoding matches")


def parse_stock(spec: str) -> list[tuple[str, int | None, bool | None]]:
    out = []
    for item in (s.strip() for s in spec.split(",") if s.strip()):
        if item == "default":
            out.append(("default", None, None))
            continue
        b, _, mode = item.partition(":")
        if not b.isdigit() or int(b) < 1 or mode not in ("sync", "async"):
            raise ValueError(f"--stock items are 'default' or B:sync / B:async, got {item!r}")
        out.append((item, int(b), mode == "async"))
    return out


def _flat_fields(fields: dict) -> dict:
    """Policy config fields with a nested dataclass (``safety_world``) as its dotted fields."""
    flat = {}
    for name, value in fields.items():
        if dataclasses.is_dataclass(value):
            flat.update({f"{name}.{k}": v for k, v in dataclasses.asdict(value).items()})
        else:
            flat[name] = value
    return flat


def _cli_value(value) -> str:
    """A config value as draccus parses it on the command line (true / false, null)."""
    if isinstance(value, bool):
        return str(value).lower()
    return "null" if value is None else str(value)


def stock_command(
    args: argparse.Namespace,
    batch: int | None,
    use_async: bool | None,
    scenes_file: Path,
    encoding: str,
    out: Path,
    safety_fields: dict | None = None,
    level=None,
) -> list[str]:
    """The ``lerobot-eval`` command line of one stock setting (the safety layer's flags included):
    the scenes file from seed 0, or a ``core.episodes.levels.Level`` from its own first seed.
    ``safety_fields``: the safety layer's knowledge of the run's world (``safety_settings``)."""
    if level is not None:
        scenes = [f"--env.level={level.name}", f"--seed={level.seed}"]
    else:
        scenes = [f"--env.scenes_file={scenes_file}", "--seed=0"]
    cmd = [
        str(BIN / "lerobot-eval"),
        f"--policy.path={args.policy_path}",
        "--policy.device=cpu",
        "--env.type=formation",
        f"--env.obstacle_encoding={encoding}",
        *scenes,
        f"--env.episode_length={args.episode_length}",
        f"--eval.n_episodes={args.episodes}",
        f"--output_dir={out}",
    ]
    cmd += [f"--policy.num_candidates={args.candidates}", f"--policy.safety_filter={args.safety_filter}"]
    if args.candidates != 1 or args.safety_filter != "none":
        for field, value in _flat_fields(safety_fields or {}).items():
            cmd.append(f"--policy.{field}={_cli_value(value)}")
    if batch is not None:
        cmd += [f"--eval.batch_size={batch}", f"--eval.use_async_envs={'true' if use_async else 'false'}"]
    return cmd


def run_stock(
    name: str,
    batch: int | None,
    use_async: bool | None,
    args: argparse.Namespace,
    scenes_file: Path,
    encoding: str,
    out: Path,
    threads: int,
    safety_fields: dict | None = None,
    level=None,
) -> dict:
    cmd = stock_command(args, batch, use_async, scenes_file, encoding, out, safety_fields, level)
    env = {
        **os.environ,
        "HF_HUB_OFFLINE": "1",
        "HF_DATASETS_OFFLINE": "1",
        "OMP_NUM_THREADS": str(threads),
        "TOKENIZERS_PARALLELISM": "false",
    }
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"lerobot-eval ({name}) failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    overall = json.loads((out / "eval_info.json").read_text())["overall"]
    return {
        "name": name,
        "wall_s": wall,
        "eval_s": float(overall["eval_s"]),
        "success": float(overall["pc_success"]) / 100,
        "n_episodes": int(overall["n_episodes"]),
        "command": " ".join(cmd[:1] + [c for c in cmd[1:] if not c.startswith("--output_dir")]),
    }


def main(argv: list[str] | None = None) -> int:
    from lerobot_formation.core.world.sampling import UNSEEN_SEED_START

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--policy.path", dest="policy_path", required=True, help="checkpoint folder")
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument(
        "--scenes", default=None, help="random:N (default, N = --episodes), dataset:N or FILE.json"
    )
    ap.add_argument("--seed", type=int, default=UNSEEN_SEED_START, help="first seed of random:N")
    ap.add_argument(
        "--level",
        default=None,
        help="a graded level (level0 .. level5): its scenes and conditions, both paths",
    )
    ap.add_argument("--dataset.root", dest="dataset_root", default=None, help="for --scenes dataset:N")
    ap.add_argument("--episode-length", type=int, default=600, help="control steps before a timeout")
    ap.add_argument("--stock", default=None, help=f"lerobot-eval settings (default: {DEFAULT_STOCK})")
    add_threads_argument(ap, "torch threads, both paths")
    ap.add_argument("--candidates", type=int, default=1, help="best-of-K of the policy's safety layer")
    ap.add_argument(
        "--safety-filter", choices=("none", "cbf"), default="none", help="the policy's per-action filter"
    )
    ap.add_argument("--out", default=None, help="keep lerobot-eval's outputs here (default: a temp dir)")
    ap.add_argument(
        "--quick", action="store_true", help="smoke run: 10 episodes of 60 steps, 3 stock settings"
    )
    args = ap.parse_args(argv)
    if args.quick:
        args.episodes = min(args.episodes, 10)
        args.episode_length = min(args.episode_length, 60)
        args.stock = args.stock or QUICK_STOCK
    try:
        stock = parse_stock(args.stock or DEFAULT_STOCK)
    except ValueError as e:
        ap.error(str(e))
    if args.candidates < 1:
        ap.error(f"--candidates must be >= 1, got {args.candidates}")
    safety = args.candidates != 1 or args.safety_filter != "none"
    if args.level and args.scenes:
        ap.error(f"--level {args.level} fixes the scenes; drop --scenes {args.scenes}")

    import torch  # noqa: F401 (loaded before apply_threads sets its thread count)

    from lerobot_formation.bench.controllers import safety_settings
    from lerobot_formation.bench.diffusion_controller import DiffusionController
    from lerobot_formation.bench.evaluation import evaluate
    from lerobot_formation.bench.scene_sets import level_scenes, parse_scenes
    from lerobot_formation.core.episodes.metrics import two_proportion_z
    from lerobot_formation.core.episodes.rollout import SUCCESS
    from lerobot_formation.core.world.dynamics import FormationParams
    from lerobot_formation.core.world.scene_files import save_scenes

    threads = apply_threads(args.threads)
    level, conditions = None, None
    if args.level:
        from lerobot_formation.core.episodes.levels import get_level

        try:
            level = get_level(args.level)
        except ValueError as e:
            ap.error(str(e))
        conditions = level.conditions
        scenes = level_scenes(level.name, args.episodes)
    else:
        scenes = parse_scenes(
            args.scenes or f"random:{args.episodes}", args.seed, args.dataset_root, args.policy_path
        )
    safety_fields = safety_settings(conditions) if safety else {}
    if len(scenes) < args.episodes:
        ap.error(f"--scenes gives {len(scenes)} scenes, fewer than --episodes {args.episodes}")
    scenes = scenes[: args.episodes]
    encoding = checkpoint_encoding(args.policy_path)
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="bench_eval_speed_"))
    out.mkdir(parents=True, exist_ok=True)
    scenes_file = out / "scenes.json"
    save_scenes(scenes, scenes_file)
    print(
        f"{args.episodes} episodes of at most {args.episode_length} steps, policy {args.policy_path} "
        f"(safety layer: K={args.candidates}, filter {args.safety_filter}) "
        f"(env encoding {encoding!r}), scenes {level.name if level else args.scenes or f'random:{args.episodes}'} -> {scenes_file}; "
        f"conditions {conditions.changed() if conditions is not None else 'none'}; "
        f"torch threads {threads}, {os.cpu_count()} CPUs",
        flush=True,
    )

    # Engine.
    t0 = time.perf_counter()
    # the policy's own safety layer, as lerobot-eval's --policy.num_candidates/safety_filter
    ctrl = DiffusionController(
        args.policy_path,
        overrides={"num_candidates": args.candidates, "safety_filter": args.safety_filter, **safety_fields},
    )
    load_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    rec = evaluate(ctrl, scenes, FormationParams(max_steps=args.episode_length), conditions=conditions)
    engine_s = time.perf_counter() - t0
    engine_success = float(np.mean(rec.outcome == SUCCESS))
    print(
        f"engine: {engine_s:.1f} s for {len(scenes)} episodes ({ctrl.stats['replans']} episode replans), policy load "
        f"{load_s:.1f} s; success {engine_success:.0%}",
        flush=True,
    )

    # Stock lerobot-eval.
    results = []
    try:
        for name, batch, use_async in stock:
            r = run_stock(
                name,
                batch,
                use_async,
                args,
                scenes_file,
                encoding,
                out / f"lerobot_eval_{name.replace(':', '_')}",
                threads,
                safety_fields,
                level,
            )
            results.append(r)
            print(
                f"lerobot-eval {name:>9}: eval_s {r['eval_s']:7.1f} s, whole command {r['wall_s']:7.1f} s, "
                f"success {r['success']:.0%} of {r['n_episodes']}; "
                f"{r['eval_s'] / engine_s:.1f}x the engine",
                flush=True,
            )
    finally:
        if not args.out:
            shutil.rmtree(out, ignore_errors=True)
    if not results:
        return 0
    n = len(scenes)
    for r in results:
        z = two_proportion_z(
            round(engine_success * n), n, round(r["success"] * r["n_episodes"]), r["n_episodes"]
        )
        print(
            f"success engine {engine_success:.1%} vs lerobot-eval {r['name']} {r['success']:.1%}: "
            f"z = {z:+.2f} ({'within noise' if abs(z) < 1.96 else 'NOT within noise'})"
        )
    best = min(results, key=lambda r: r["eval_s"])
    default = next((r for r in results if r["name"] == "default"), None)
    if default is not None:
        print(
            f"lerobot-eval default settings: {default['eval_s']:.1f} s ({default['eval_s'] / engine_s:.1f}x the engine)"
        )
    print(f"lerobot-eval fastest setting: {best['name']} ({best['eval_s']:.1f} s): {best['command']}")
    print(
        f"whole commands: lerobot-eval {best['name']} {best['wall_s']:.1f} s vs engine load + evaluate "
        f"{load_s + engine_s:.1f} s: {best['wall_s'] / (load_s + engine_s):.1f}x"
    )
    print(f"ratio lerobot-eval best / engine (evaluation time): {best['eval_s'] / engine_s:.1f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
