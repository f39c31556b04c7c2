"""The first look (``scripts/run.sh demo``, about 30 s on an idle 2-core CPU once set up): the
pretrained default, with standard sampling (``diffusion``) and with its safety layer
(``diffusion-safe``), against the paper's baselines PAC and MPPI on the first 6 scenes of the hardest
level (``level5:6``: structures sensed within 3 m, noisy, one step late, rate limited, two moving
obstacles; seeds from 1,000,000 on, which no training dataset uses). It writes results.json,
tables.md and three figures (the controllers side by side, the default's trajectories, the success
chart) to outputs/demo, then prints each controller's success on those scenes with its Wilson
95 % interval. Six scenes give wide intervals: the README's table has hundreds per level.

Extra arguments are passed on to ``lerobot-formation-bench`` (later ones win: ``--scenes level5:100``
is a larger look, ``--unseen hard:20`` adds a second set for the diffusion controllers).
``--all-figures`` (the demo's own flag) draws every figure the bench draws instead of the three. The
demo before the 30-second version is ``--controllers pac,mppi,diffusion,diffusion-bestof --scenes
random:50 --unseen hard:20 --all-figures`` (``PREVIOUS_ARGUMENTS``; benchmarks/bench_demo_time.py
times the two beside each other)."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

from lerobot_formation.bench import cli as bench_cli
from lerobot_formation.bench.scene_sets import scene_set_level
from lerobot_formation.core.world.sampling import UNSEEN_SEED_START

# the repository root's pretrained/ (this file is lerobot_formation/bench/demo.py)
PRETRAINED = Path(__file__).resolve().parents[2] / "pretrained" / "formation_diffusion_route_v1"
CONTROLLERS = "pac,mppi,diffusion,diffusion-safe"
SCENES = "level5:6"
# the controllers run two at a time on a machine with two cores or more (the same numbers as one by one)
JOBS = min(2, os.cpu_count() or 1)
FOCUS = "diffusion-safe"  # the controller whose own figures the demo draws (the default with its layer)
ALL_FIGURES = "--all-figures"
# the demo's arguments before it was cut to 30 s (about 70 s): the default (standard sampling and
# best-of-10) against PAC and MPPI on 50 paper-layout scenes, the diffusion controllers on 20 hard ones
PREVIOUS_ARGUMENTS = [
    "--controllers", "pac,mppi,diffusion,diffusion-bestof",
    "--scenes", "random:50",
    "--unseen", "hard:20",
    ALL_FIGURES,
]  # fmt: skip
LABELS = {
    "pac": "PAC (the paper's potential field)",
    "mppi": "MPPI (the paper's sampling MPC)",
    "route-pursuit": "route pursuit (no network)",
    "route-pursuit-safe": "route pursuit + the safety layer",
    "diffusion": "default, standard sampling",
    "diffusion-bestof": "default, best-of-10",
    "diffusion-safe": "default + its safety layer",
    "diffusion-policy": "default as its config stores it",
}


def default_arguments() -> list[str]:
    """The bench arguments of the demo: the default against PAC and MPPI; only PAC and MPPI when the
    checkpoint folder is missing (an installed package without the repository)."""
    if (PRETRAINED / "config.json").is_file():
        return [
            "--controllers", CONTROLLERS,
            "--policy.path", str(PRETRAINED),
            "--scenes", SCENES,
            "--out", "outputs/demo",
            "--jobs", str(JOBS),
        ]  # fmt: skip
    print(f"demo: no pretrained default at {PRETRAINED}; running PAC and MPPI only")
    return ["--controllers", "pac,mppi", "--scenes", SCENES, "--out", "outputs/demo"]


def draw_demo_figures(out, results, records, scene_sets, specs, seed):
    """The demo's three figures, drawn by the bench in place of its full set (same arguments and return
    value as ``bench.figures.draw_bench_figures``): per scene set the trajectories of the default with
    its layer (of every controller where it did not run) and the controllers side by side, then the
    success chart. A figure that raises is reported as one ``warning:`` line and skipped."""
    from lerobot_formation.bench import figures as bench_figures
    from lerobot_formation.bench.plots import plot_trajectories, scene_set_label
    from lerobot_formation.bench.scene_sets import scene_set_presets

    failed: list[str] = []

    def attempt(what: str, draw, *args, **kwargs):
        try:
            return draw(*args, **kwargs)
        except Exception as e:  # noqa: BLE001  (a figure never costs the results; say which failed)
            failed.append(f"figure {what} not drawn: {type(e).__name__}: {e}")
            print(f"warning: {failed[-1]}", file=sys.stderr)
            return None

    drawn: set[str] = set()
    for label, recs in records.items():
        spec, scenes = specs.get(label, ""), scene_sets[label]
        presets = scene_set_presets(spec, len(scenes)) if spec else None
        for name in [n for n in recs if n == FOCUS] or list(recs):
            rec, stem = recs[name], f"{name}_{label}_trajectories.png"
            title = f"{name} on {scene_set_label(spec, seed)}" if spec else name
            shown = list(range(min(6, len(rec))))
            path = attempt(
                stem, plot_trajectories, rec, scenes, shown, out / stem, title=title, presets=presets
            )
            if path is not None:
                results[label][name]["figures"].append(path.name)
                drawn.add(path.name)
        if len(recs) > 1:
            shared = attempt(
                f"controllers_{label}.png",
                bench_figures.write_comparison_figure,
                out,
                label,
                recs,
                scenes,
                spec,
                seed,
            )
            if shared:
                for name in recs:
                    results[label][name]["figures"].append(shared)
                drawn.add(shared)
    success = attempt("success_rates.png", bench_figures.write_success_figure, out, results, specs, seed)
    return sorted(drawn) + ([success] if success else []), failed


def summary_lines(results: dict) -> list[str]:
    """Each scene set's controllers with their successes of n, percent and Wilson 95 % interval, then
    what so few scenes can and cannot say."""
    lines = []
    meta = results.get("meta", {})
    sets = results.get("by_scenes", {})
    n_max = 0
    for label, res in sets.items():
        spec = meta.get("unseen") if label == "unseen" else meta.get("scenes")
        lines.append(f"demo: success on {spec or label} (unseen scenes), with Wilson 95 % intervals:")
        width = max(len(LABELS.get(name, name)) for name in res)
        for name, r in res.items():
            n = r["n_episodes"]
            k = round(r["success_rate"] * n)
            lo, hi = r["success_ci95"]
            n_max = max(n_max, n)
            lines.append(
                f"demo:   {LABELS.get(name, name):<{width}}  {k:>3} of {n:<3} {r['success_rate']:6.1%} "
                f"[{lo:.0%}, {hi:.0%}]  ({name})"
            )
    if sets and n_max < 100:
        lines.append(
            f"demo: {n_max} scenes are a first look: where two intervals overlap, this run does not tell the "
            "controllers apart; the README's table has hundreds of scenes per level (--scenes level5:100 "
            "is a larger look)"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    all_figures = ALL_FIGURES in argv
    argv = [a for a in argv if a != ALL_FIGURES]
    defaults = default_arguments()
    args = bench_cli.build_parser().parse_args(defaults + argv)
    seed = UNSEEN_SEED_START if args.seed is None else args.seed
    if args.unseen:  # say what the two sets are: both unseen, the second the hard suite
        print(
            f"demo: {args.controllers} on {args.scenes}, then the diffusion controllers on {args.unseen}; "
            f"scene seeds from {seed} on, which no training dataset uses (both sets are unseen)"
        )
    else:
        try:
            level = scene_set_level(args.scenes)
        except ValueError:  # an unknown level: the bench says so
            level = None
        what = f" ({level.name}: {level.title})" if level is not None else ""
        print(
            f"demo: {args.controllers} on {args.scenes}{what}; scene seeds from {seed} on, which no "
            "training dataset uses (unseen scenes)"
        )
    start = time.time()
    # the demo's folder is its own: a new demo replaces the last one (unless --resume is asked for)
    replace = [] if {"--resume", "--overwrite"} & set(argv) else ["--overwrite"]
    full = bench_cli.draw_bench_figures
    if not all_figures:  # three figures, not the bench's full set (about 20 for four controllers)
        bench_cli.draw_bench_figures = draw_demo_figures
    try:
        code = bench_cli.main(defaults + replace + argv)
    finally:
        bench_cli.draw_bench_figures = full
    if code == 0:  # the summary, then the last line names what to open (the figures were listed above)
        out = Path(args.out)
        results_file = out / "results.json"
        if results_file.is_file():
            print("\n".join(summary_lines(json.loads(results_file.read_text()))))
        pngs = [p for p in out.glob("*.png") if p.stat().st_mtime >= start - 1] if not args.no_figures else []
        figures = f" and the {len(pngs)} figures listed above" if pngs else ""
        print(f"demo: done in {time.time() - start:.1f} s; open {out / 'tables.md'}{figures}")
    return code


if __name__ == "__main__":
    raise SystemExit(main())
