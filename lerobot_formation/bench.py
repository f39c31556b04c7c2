"""``lerobot-formation-bench``: the paper's experiments in one command.

Runs controllers on a scene set with the batched evaluation engine, computes every SPEC metric
(Wilson 95 % intervals on success), and writes ``results.json``, ``tables.md`` (the paper's two
tables with its own numbers beside ours) and PNG figures.

Example::

    lerobot-formation-bench --controllers pac,mppi,diffusion,diffusion-adaptive \\
        --policy.path pretrained/formation_diffusion_cpu --scenes dataset:100 --unseen random:100 \\
        --seed 1000000 --out outputs/bench

Scenes: ``random:N`` (the valid scenes of seeds S..S+N-1, S = --seed, default 1_000_000, which the
dataset never uses; ``<preset>:N`` the same from a scene preset of ``core.scene.SCENE_PRESETS``, e.g.
``gates:25``; ``hard:N`` N/4 scenes of each of gates, blockers, dense and goals), the
``dataset:N`` (the first N episodes of a dataset: ``--dataset.root``, or the
``dataset_scenes.json`` shipped with the policy), or a scenes JSON file. ``--unseen random:N`` also
runs the diffusion controllers on unseen scenes for the standard-vs-adaptive table.

Bad input (arguments, scene files, a ``--policy.path`` that is missing, incomplete, broken or of
another policy type, a controller the checkpoint cannot serve) is one line ``error: ...`` on stderr
and exit code 2. If a controller fails after others finished, ``results.json`` and ``tables.md`` are
still written with the finished ones (``meta.incomplete``, ``meta.error``) before the error.
Clearance metrics are null (n/a in the tables) for scenes with no obstacle.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from lerobot_formation.core.dynamics import FormationParams
from lerobot_formation.core.metrics import episode_metrics, summarize
from lerobot_formation.core.rollout import OUTCOME_NAMES, EpisodeRecords, PACController
from lerobot_formation.core.scene import (
    HARD_PRESETS,
    SCENE_PRESETS,
    UNSEEN_SEED_START,
    SamplingReport,
    Scenes,
    load_scenes,
    sample_scenes,
    scene_preset,
    scenes_from_frames,
)
from lerobot_formation.evaluation import evaluate
from lerobot_formation.threads import add_threads_argument, apply_threads


def _diffusion(candidates: bool, safety_filter: str | None, adaptive: bool = False):
    """A factory of a diffusion controller: ``candidates`` True takes --candidates, else K = 1;
    ``safety_filter`` None is the world-frame adaptive rule (or standard), "none"/"cbf" the policy's
    own safety layer (core.safety)."""

    def factory(name: str, params: FormationParams, args: argparse.Namespace, bundle=None):
        from lerobot_formation.diffusion_controller import DiffusionController

        return DiffusionController(
            args.policy_path,
            candidates=args.candidates if candidates else 1,
            adaptive=adaptive,
            num_inference_steps=args.num_inference_steps,
            seed=args.seed_policy,
            params=params,
            policy_bundle=bundle,
            safety_filter=safety_filter,
            name=name,
        )

    return factory


def _pac(name, params, args, bundle=None):
    return PACController(params=params)


def _mppi(name, params, args, bundle=None):
    from lerobot_formation.core.mppi import MPPIConfig, MPPIController

    return MPPIController(MPPIConfig(seed=args.seed_policy), params)


# Controllers by name: a factory (name, params, args, policy bundle) -> controller. A new controller is
# one line here (the engine needs only reset(scenes) and act(state, idx), core/rollout.py).
CONTROLLER_FACTORIES = {
    "pac": _pac,
    "mppi": _mppi,
    "diffusion": _diffusion(False, None),  # standard: one sample per replan
    "diffusion-adaptive": _diffusion(True, None, adaptive=True),  # best-of-K, world-frame cost-to-go rule
    "diffusion-bestof": _diffusion(True, "none"),  # the policy's best-of-K (footprint, then progress)
    "diffusion-cbf": _diffusion(False, "cbf"),  # one sample, CBF filter on every action
    "diffusion-safe": _diffusion(True, "cbf"),  # best-of-K and the CBF filter
}
CONTROLLERS = tuple(CONTROLLER_FACTORIES)

# The paper's Table "Three-way controller comparison on dataset" (100 episodes) and Table "Standard
# vs adaptive"; mean and std as printed.
PAPER_THREE_WAY = {
    "success_rate": (
        "Success Rate (%)",
        {"mppi": 65.0, "diffusion": 62.0, "pac": 100.0, "diffusion-adaptive": 70.0},  # adaptive: Table 2
    ),
    "path_length": (
        "Path Length (m)",
        {"mppi": (9.35, 1.52), "diffusion": (9.12, 1.33), "pac": (9.38, 1.83)},
    ),
    "path_optimality": (
        "Path Optimality",
        {"mppi": (0.775, 0.120), "diffusion": (0.791, 0.110), "pac": (0.780, 0.133)},
    ),
    "tracking_deviation": (
        "Tracking Deviation (m)",
        {"mppi": (1.067, 0.447), "diffusion": (1.064, 0.419), "pac": (1.139, 0.513)},
    ),
    "min_clearance": (
        "Min Clearance (m)",
        {"mppi": (0.440, 0.193), "diffusion": (0.305, 0.237), "pac": (0.488, 0.140)},
    ),
    "mean_clearance": (
        "Mean Clearance (m)",
        {"mppi": (0.974, 0.164), "diffusion": (0.895, 0.174), "pac": (1.078, 0.180)},
    ),
    "mean_control": (
        "Mean Control Magnitude",
        {"mppi": (0.602, 0.079), "diffusion": (0.370, 0.031), "pac": (0.452, 0.050)},
    ),
    "control_smoothness": (
        "Control Smoothness",
        {"mppi": (4.538, 1.151), "diffusion": (0.336, 0.102), "pac": (1.164, 0.650)},
    ),
    "energy": ("Energy Usage", {"mppi": (10.20, 3.11), "diffusion": (5.31, 1.34), "pac": (6.95, 2.00)}),
    "time": ("Time (s)", {"mppi": (25.98, 10.20), "diffusion": (31.05, 6.75), "pac": (27.81, 6.49)}),
    "mean_velocity": (
        "Mean Velocity (m/s)",
        {"mppi": (0.390, 0.084), "diffusion": (0.297, 0.023), "pac": (0.340, 0.040)},
    ),
    "mean_curvature": (
        "Mean Curvature",
        {"mppi": (28.29, 52.73), "diffusion": (0.787, 0.606), "pac": (0.733, 0.388)},
    ),
    "peak_curvature": (
        "Peak Curvature",
        {"mppi": (6767, 15229), "diffusion": (5.28, 2.77), "pac": (5.51, 3.57)},
    ),
    "jerk": ("Motion Jerk", {"mppi": (23.10, 3.51), "diffusion": (0.359, 0.055), "pac": (0.576, 0.114)}),
    "orientation_stability": (
        "Orientation Stability",
        {"mppi": (0.202, 0.028), "diffusion": (0.188, 0.023), "pac": (0.225, 0.026)},
    ),
}
EXTRA_ROWS = {
    "formation_min_clearance": "Formation Min Clearance (m), all episodes",
    "final_formation_error": "Final Formation Error (m)",
    "mean_follower_velocity_error": "Mean Follower Velocity Error (m/s)",
}
PAPER_ADAPTIVE = {
    ("unseen", "diffusion"): 25.0,
    ("unseen", "diffusion-adaptive"): 26.0,
    ("dataset", "diffusion"): 62.0,
}
PAPER_ADAPTIVE[("dataset", "diffusion-adaptive")] = 70.0
SET_TITLES = {
    "unseen": "Random seeds (unseen)",
    "random": "Random seeds (unseen)",
    "dataset": "Dataset episodes",
}


# -- scenes ------------------------------------------------------------------------------------------
def dataset_scenes(root: str | Path, n: int) -> Scenes:
    """Scenes of the first n episodes of a dataset made by ``generate_pac_dataset``."""
    import pyarrow.parquet as pq

    files = sorted(Path(root).glob("data/*/*.parquet"))
    if not files:
        raise ValueError(f"--dataset.root {root} holds no data/*/*.parquet files")
    cols = ["frame_index", "episode_index", "scene.seed", "scene.obstacles", "scene.goal", "scene.start"]
    rows = []
    for f in files:
        try:
            t = pq.read_table(f, columns=cols, filters=[("frame_index", "=", 0)])
        except Exception as e:  # a dataset without scene columns
            raise ValueError(f"{f} lacks the scene.* columns of generate_pac_dataset: {e}") from e
        rows.append(t)
    import pyarrow as pa

    t = pa.concat_tables(rows).sort_by("episode_index").slice(0, n)
    if len(t) < n:
        raise ValueError(f"dataset {root} has {len(t)} episodes, fewer than the {n} asked for")
    return scenes_from_frames(
        np.asarray(t["scene.obstacles"].to_pylist()),
        np.asarray(t["scene.goal"].to_pylist()),
        np.asarray(t["scene.start"].to_pylist()),
        np.asarray(t["scene.seed"].to_pylist()),
    )


def parse_scenes(
    spec: str,
    seed: int,
    dataset_root: str | None = None,
    policy_path: str | None = None,
    report: SamplingReport | None = None,
) -> Scenes:
    """``random:N``, ``dataset:N`` or a path to a scenes JSON file. ``report`` counts rejected draws."""
    kind, _, count = spec.partition(":")
    if kind in ("random", "dataset", "hard") or kind in SCENE_PRESETS:
        try:
            n = int(count)
        except ValueError as e:
            raise ValueError(f"--scenes {kind}:N needs an integer N, got {spec!r}") from e
        if n < 1:
            raise ValueError(f"--scenes {kind}:N needs N >= 1, got {n}")
        if kind == "random":
            return sample_scenes(seed + np.arange(n), report=report)
        if kind in SCENE_PRESETS:
            return sample_scenes(seed + np.arange(n), scene_preset(kind), report=report)
        if kind == "hard":  # N/4 scenes of each hard preset, seeds seed.. of each
            k = len(HARD_PRESETS)
            sizes = [n // k + (1 if i < n % k else 0) for i in range(k)]
            return Scenes.concat(
                [
                    sample_scenes(seed + np.arange(m), scene_preset(p), report=report)
                    for p, m in zip(HARD_PRESETS, sizes, strict=True)
                    if m
                ]
            )
        if dataset_root:
            return dataset_scenes(dataset_root, n)
        shipped = Path(policy_path or "") / "dataset_scenes.json"
        if policy_path and shipped.is_file():
            scenes = load_scenes(shipped)
            if len(scenes) < n:
                raise ValueError(f"{shipped} holds {len(scenes)} scenes, fewer than {n}")
            return scenes[:n]
        raise ValueError(
            "--scenes dataset:N needs --dataset.root, or a --policy.path with dataset_scenes.json"
        )
    return load_scenes(spec)


# -- controllers -------------------------------------------------------------------------------------
def make_controller(name: str, params: FormationParams, args: argparse.Namespace, bundle=None):
    if name not in CONTROLLER_FACTORIES:
        raise ValueError(f"unknown controller {name!r}; choose from {CONTROLLERS}")
    return CONTROLLER_FACTORIES[name](name, params, args, bundle)


# -- results -----------------------------------------------------------------------------------------
def _clean(x):
    if isinstance(x, float | np.floating):
        return None if not np.isfinite(x) else float(x)
    if isinstance(x, np.integer | np.bool_):
        return x.item()
    return x


def controller_results(rec: EpisodeRecords, scenes: Scenes) -> dict:
    per = episode_metrics(rec, scenes.start, scenes.goal)
    summary = summarize(per)
    episodes = []
    for b in range(len(rec)):
        e = {
            "seed": int(scenes.seeds[b]),
            "outcome": OUTCOME_NAMES[int(rec.outcome[b])],
            "steps": int(rec.steps[b]),
        }
        e.update({k: _clean(v[b]) for k, v in per.items() if k not in ("success", "collision", "timeout")})
        episodes.append(e)
    summary["episodes"] = episodes
    return summary


def _fmt(mean, std, digits=3):
    if mean is None:
        return "n/a"
    return f"{mean:.{digits}g} ± {std:.{digits}g}" if std is not None else f"{mean:.{digits}g}"


def three_way_table(results: dict, label: str) -> str:
    cols = [
        c for c in ("mppi", *[n for n in CONTROLLERS if n.startswith("diffusion")], "pac") if c in results
    ]
    head = "| Metric | " + " | ".join(f"{c} (ours) | {c} (paper)" for c in cols) + " |"
    lines = [f"### Three-way comparison on {label}", "", head, "|---" * (1 + 2 * len(cols)) + "|"]
    for key, (title, paper) in PAPER_THREE_WAY.items():
        row = [title]
        for c in cols:
            r = results[c]
            if key == "success_rate":
                lo, hi = r["success_ci95"]
                row.append(f"{100 * r['success_rate']:.1f} [{100 * lo:.0f}, {100 * hi:.0f}]")
                row.append(f"{paper[c]:.1f}" if c in paper else "—")
            else:
                m = r.get(key) or {}
                row.append(_fmt(m.get("mean"), m.get("std")))
                p = paper.get(c) if c in ("mppi", "diffusion", "pac") else None
                row.append(_fmt(*p) if p else "—")
        lines.append("| " + " | ".join(row) + " |")
    for key, title in EXTRA_ROWS.items():
        row = [title]
        for c in cols:
            m = results[c].get(key) or {}
            row += [_fmt(m.get("mean"), m.get("std")), "—"]
        lines.append("| " + " | ".join(row) + " |")
    n = {c: results[c]["n_episodes"] for c in cols}
    lines += [
        "",
        f"Episodes per controller: {n}. Success in % with Wilson 95 % interval. Path and motion rows are "
        "mean ± std over successful episodes; the formation minimum clearance is over all episodes.",
        "",
    ]
    return "\n".join(lines)


def adaptive_table(by_set: dict[str, dict], specs: dict[str, str] | None = None) -> str:
    """Success of every diffusion controller per scene set; ``specs`` maps a set to its --scenes value
    (the paper's numbers are shown only for the paper's protocols)."""
    specs = specs or {}
    lines = [
        "### Standard vs adaptive diffusion policy",
        "",
        "| Scenes | Method | Success % (ours) [95 % CI] | Collisions | Timeouts | Success % (paper) |",
        "|---|---|---|---|---|---|",
    ]
    for set_name, results in by_set.items():
        for c in [n for n in CONTROLLERS if n.startswith("diffusion")]:
            if c not in results:
                continue
            r = results[c]
            lo, hi = r["success_ci95"]
            spec = specs.get(set_name, "")
            paper_protocol = spec.split(":")[0] in ("random", "dataset", "")
            key = "unseen" if set_name == "random" else set_name
            paper = PAPER_ADAPTIVE.get((key, c)) if paper_protocol else None
            title = SET_TITLES.get(set_name, set_name + " scenes") if paper_protocol else f"{spec} (unseen)"
            lines.append(
                f"| {title} | "
                f"{'Standard' if c == 'diffusion' else c} | {100 * r['success_rate']:.1f} "
                f"[{100 * lo:.0f}, {100 * hi:.0f}] | {r['collisions']} | {r['timeouts']} | "
                f"{paper if paper is not None else '—'} |"
            )
    return "\n".join(lines) + "\n"


def write_figures(out: Path, name: str, rec: EpisodeRecords, scenes: Scenes, title: str = "") -> list[str]:
    """The per-controller figures, files named ``name``_*.png, titled ``title`` (default ``name``)."""
    from lerobot_formation.plots import (
        plot_failures,
        plot_final_error_histogram,
        plot_formation_errors,
        plot_trajectories,
    )

    title = title or name
    shown = list(range(min(6, len(rec))))  # the same first scenes for every controller
    files = [
        plot_trajectories(rec, scenes, shown, out / f"{name}_trajectories.png", title=title),
        plot_formation_errors(rec, shown, out / f"{name}_formation_error.png", title=title, scenes=scenes),
        plot_final_error_histogram(rec, out / f"{name}_final_error_hist.png", title=title),
    ]
    if (rec.outcome != 1).any():
        files.append(plot_failures(rec, scenes, out / f"{name}_failures.png", title=title))
    return [f.name for f in files]


def write_comparison_figure(
    out: Path,
    label: str,
    records: dict[str, EpisodeRecords],
    scenes: Scenes,
    spec: str = "",
    seed: int = UNSEEN_SEED_START,
) -> str:
    from lerobot_formation.plots import comparison_scenes, plot_controller_comparison, scene_set_label

    path = out / f"controllers_{label}.png"
    title = scene_set_label(spec, seed) if spec else label
    return plot_controller_comparison(records, scenes, comparison_scenes(records, 3), path, title=title).name


def write_success_figure(out: Path, results: dict[str, dict], specs: dict[str, str], seed: int) -> str:
    from lerobot_formation.plots import plot_success_rates, scene_set_label

    # Each set named by what it is (the demo's two sets are both unseen; the second is the hard suite).
    counts = {}
    for s, res in results.items():
        name = scene_set_label(specs[s], seed)
        name = f"{name} ({specs[s]})" if name in counts else name  # e.g. random:50 and random:20
        counts[name] = {
            c: (round(r["success_rate"] * r["n_episodes"]), r["n_episodes"]) for c, r in res.items()
        }
    return plot_success_rates(counts, out / "success_rates.png").name


class BenchInputError(ValueError):
    """A bad input found while running (a controller that this checkpoint cannot serve, ...): reported
    as one ``error:`` line, exit code 2, after writing the results of the controllers that finished."""


def run_set(
    names, scenes, params, args, out: Path, label: str, bundle, figures: bool, into: dict | None = None
) -> dict:
    """Run the controllers ``names`` on ``scenes``; each finished controller's entry is put into
    ``into`` (default: a new dict, returned) at once, so a later failure keeps it."""
    results, records = (into if into is not None else {}), {}
    spec = (args.unseen if label == "unseen" else args.scenes) or ""
    for name in names:
        t0 = time.perf_counter()
        try:
            ctrl = make_controller(name, params, args, bundle)
        except ValueError as e:
            raise BenchInputError(f"controller {name}: {e}") from e
        # Progress bars only on a terminal (tqdm writes to stderr), so logs stay free of them.
        progress = not args.no_progress and sys.stderr.isatty()
        rec = evaluate(ctrl, scenes, params, progress=progress, desc=f"{name} ({label})")
        entry = controller_results(rec, scenes)
        entry["wall_time_s"] = time.perf_counter() - t0
        if getattr(ctrl, "stats", None):  # the safety layer's interventions
            st = dict(ctrl.stats)
            st["filter_intervention_rate"] = st["filter_interventions"] / max(st["steps"], 1)
            st["replans_none_safe_rate"] = st["replans_none_safe"] / max(st["replans"], 1)
            entry["safety"] = st
        entry["scenes"] = label
        if figures:
            from lerobot_formation.plots import scene_set_label  # matplotlib only when drawing

            title = f"{name} on {scene_set_label(spec, args.seed)}" if spec else ""
            entry["figures"] = write_figures(out, f"{name}_{label}", rec, scenes, title)
            records[name] = rec
        results[name] = entry
        lo, hi = entry["success_ci95"]
        print(
            f"[{label}] {name}: success {entry['success_rate']:.1%} [{lo:.0%}, {hi:.0%}] of {entry['n_episodes']} "
            f"(collisions {entry['collisions']}, timeouts {entry['timeouts']}) in {entry['wall_time_s']:.1f} s",
            flush=True,
        )
    if figures and len(records) > 1:
        shared = write_comparison_figure(out, label, records, scenes, spec, args.seed)
        for entry in results.values():
            entry["figures"].append(shared)
    return results


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="lerobot-formation-bench", description=__doc__.split("\n")[0])
    ap.add_argument("--controllers", default="pac", help=f"comma-separated, from {CONTROLLERS}")
    ap.add_argument(
        "--scenes",
        default="random:20",
        help="random:N, <preset>:N (paper, wide, gates, blockers, dense, goals), hard:N, dataset:N or FILE.json",
    )
    ap.add_argument(
        "--unseen", default=None, help="also run the diffusion controllers on these scenes (random:N)"
    )
    ap.add_argument("--seed", type=int, default=UNSEEN_SEED_START, help="first seed for random:N")
    ap.add_argument("--policy.path", dest="policy_path", default=None, help="LeRobot checkpoint folder")
    ap.add_argument("--dataset.root", dest="dataset_root", default=None, help="dataset for dataset:N")
    ap.add_argument("--candidates", type=int, default=10, help="K of the adaptive policy")
    ap.add_argument(
        "--num-inference-steps", type=int, default=None, help="DDIM steps (default: checkpoint's)"
    )
    ap.add_argument("--seed-policy", type=int, default=0, help="seed of the policies' noise")
    ap.add_argument("--out", default="outputs/bench", help="output folder")
    ap.add_argument("--no-figures", action="store_true", help="write results.json and tables.md only")
    ap.add_argument(
        "--no-progress",
        action="store_true",
        help="no progress bars (there are none either when stderr is not a terminal); the summary "
        "lines are always printed",
    )
    add_threads_argument(ap, "torch threads of the diffusion controllers")
    return ap


def _fail(message: str):
    """One line ``error: ...`` on stderr and exit code 2 (bad input; no traceback)."""
    print(f"error: {message}", file=sys.stderr)
    raise SystemExit(2)


def write_results(
    out: Path, results: dict, label: str, args, report: SamplingReport, error: str | None = None
):
    """results.json and tables.md of the controllers in ``results``; ``error`` marks a run that stopped
    early (``meta.incomplete``, ``meta.error``), with what finished before it."""
    # results.json: keyed by controller for the main scene set (the world issue's keys), plus the
    # other scene sets under "by_scenes".
    payload = dict(results.get(label, {}))
    payload["by_scenes"] = {k: v for k, v in results.items()}
    payload["meta"] = {
        "scenes": args.scenes,
        "unseen": args.unseen,
        "seed": args.seed,
        "policy_path": args.policy_path,
        "candidates": args.candidates,
        "num_inference_steps": args.num_inference_steps,
        "date": time.strftime("%Y-%m-%d"),
        "scene_sampling": report.as_dict() if report.drawn else None,
        "incomplete": error is not None,
        "error": error,
    }
    tmp = out / "results.json.tmp"
    tmp.write_text(json.dumps(payload, indent=1, default=_clean))
    os.replace(tmp, out / "results.json")
    tables = [three_way_table(results.get(label, {}), f"{label} scenes ({args.scenes})")]
    sets = {k: v for k, v in results.items() if any(c.startswith("diffusion") for c in v)}
    if sets:
        tables.append(adaptive_table(sets, {label: args.scenes, "unseen": args.unseen or ""}))
    if error is not None:
        tables.append(f"**Incomplete run**: {error}\n")
    (out / "tables.md").write_text("\n".join(tables))


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    apply_threads(args.threads)
    names = [c.strip() for c in args.controllers.split(",") if c.strip()]
    for n in names:
        if n not in CONTROLLERS:
            _fail(f"unknown controller {n!r}; choose from {CONTROLLERS}")
    diffusion = [n for n in names if n.startswith("diffusion")]
    if diffusion and not args.policy_path:
        _fail(f"controllers {diffusion} need --policy.path")
    if args.candidates < 1:
        _fail(f"--candidates must be >= 1, got {args.candidates}")
    if args.num_inference_steps is not None and args.num_inference_steps < 1:
        _fail(f"--num-inference-steps must be >= 1, got {args.num_inference_steps}")
    report = SamplingReport()
    try:
        scenes = parse_scenes(args.scenes, args.seed, args.dataset_root, args.policy_path, report)
        unseen = parse_scenes(args.unseen, args.seed) if args.unseen else None
    except ValueError as e:
        _fail(str(e))
    params = FormationParams()
    out = Path(args.out)
    bundle = None
    if diffusion:
        from lerobot_formation.diffusion_controller import load_policy

        # torch's thread count is --threads (apply_threads set OMP_NUM_THREADS before torch loads).
        try:
            bundle = load_policy(args.policy_path)
        except ValueError as e:  # CheckpointError: missing, incomplete, broken or another policy type
            _fail(f"--policy.path: {e}")
        steps, most = args.num_inference_steps, bundle[0].config.num_train_timesteps
        if steps is not None and steps > most:
            _fail(
                f"--num-inference-steps must be in [1, {most}] (the checkpoint's training steps), got {steps}"
            )
    out.mkdir(parents=True, exist_ok=True)
    label = args.scenes.split(":")[0] if ":" in args.scenes else Path(args.scenes).stem
    results: dict[str, dict] = {label: {}}
    try:
        run_set(names, scenes, params, args, out, label, bundle, not args.no_figures, into=results[label])
        if unseen is not None and diffusion:
            results["unseen"] = {}
            run_set(
                diffusion, unseen, params, args, out, "unseen", bundle, not args.no_figures, results["unseen"]
            )
    except BaseException as e:  # keep what finished, then report: one line for bad input, else the traceback
        done = [f"{k}/{c}" for k, v in results.items() for c in v]
        message = str(e) if isinstance(e, BenchInputError) else f"{type(e).__name__}: {e}"
        if done:
            write_results(out, results, label, args, report, error=message)
            print(f"wrote {out / 'results.json'} with the finished controllers {done}", file=sys.stderr)
        if isinstance(e, BenchInputError):
            _fail(message)
        raise
    if not args.no_figures:
        figures = sorted({f for res in results.values() for r in res.values() for f in r["figures"]})
        specs = {label: args.scenes, "unseen": args.unseen or ""}
        figures.append(write_success_figure(out, results, specs, args.seed))
        print(f"figures in {out}: {', '.join(figures)}")
    if report.drawn:
        print(
            f"scenes: {report.accepted} valid of {report.drawn} drawn, rejection rate {report.rejection_rate:.1%} "
            f"(start covered {report.rejected_start}, obstacle near goal {report.rejected_goal}, "
            f"no passage {report.rejected_passage})"
        )
    write_results(out, results, label, args, report)
    print(f"wrote {out / 'results.json'}, {out / 'tables.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
