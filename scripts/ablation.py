"""One ablation table of the learned planner's levers, each alone and together (issue 9).

Every row is a controller (a policy checkpoint with a safety option, or a baseline) run by the batched
engine on the same scene sets; columns: success with a Wilson 95 % interval, collisions, timeouts,
control smoothness, jerk, path length, time (means over successful episodes) and, for the safety
layer, how often it intervened. Rows whose policy cannot observe a scene set (the old "grid+list"
default holds at most 5 obstacles) say so instead of a number.

    python scripts/ablation.py --new pretrained/formation_diffusion_route_v1 --old pretrained/formation_diffusion_cpu \\
        --sets random:100,hard:100 --out outputs/ablation

Conditions: a graded level's set (``--sets level5:500``) runs under that level's conditions; the other
sets under the ``--env.<field> VALUE`` flags of the bench (docs/conditions.md), which a level refuses
(``bench.scene_sets.scene_set_conditions``). ``ablation.md`` names each set's conditions.

Rows: PAC; MPPI; route pursuit (``core/controllers/route_pursuit.py``, no learning); the old default (paper data, egocentric grid+list list) standard; the
new model (wide data, "nearest" encoding) standard, best-of-K, best-of-K + escapes, CBF filter,
both, both + escapes ("escapes": ``ReplanExperiment.escape_advantage`` = ``--escape-advantage``, a safe manoeuvre
also replaces sampled chunks that make too little progress; without it, only when none is safe);
with ``--dagger CKPT`` the same model after a DAgger round; with ``--route CKPT`` the same rows for
a model observing the "nearest+route" encoding (the route hint, ``core/encodings/route_encoding.py``); with ``--n-action-steps N`` the new
model executing N instead of its trained number of actions per replan (an action-execution change);
"+ blending": ``ReplanExperiment.blend_steps`` = ``--blend-steps`` (a new chunk's first actions blended from the
executed one, ``core.safety.replan_blend``; the other rows run without it); "+ warm start":
``warm_start_step`` = ``--warm-start-step`` (a replan starts from the last chunk's unexecuted rest,
noised, every candidate with its own noise; the other rows sample from pure noise; with
``--blend-steps 0`` these rows are named without "+ blending"); "+ stop":
``ReplanExperiment.blocked_fallback`` "stop". The blending, escape and stop settings are the
replanner's experiment settings (``policy.replanner.ReplanExperiment``), not policy config fields.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from dataclasses import fields
from pathlib import Path

import numpy as np

from lerobot_formation.bench.controllers import make_controller
from lerobot_formation.bench.evaluation import evaluate
from lerobot_formation.bench.results import controller_results, safety_rates
from lerobot_formation.bench.scene_sets import parse_scenes, scene_set_conditions
from lerobot_formation.bench.settings import ControllerOptions
from lerobot_formation.core.perception.conditions import Conditions
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.core.world.sampling import UNSEEN_SEED_START
from lerobot_formation.core.world.scenes import Scenes
from lerobot_formation.envs.condition_flags import add_condition_arguments, conditions_from_flags
from lerobot_formation.policy.replanner import ReplanExperiment

EXPERIMENT_FIELDS = {f.name for f in fields(ReplanExperiment)}


def row_specs(args) -> list[tuple[str, str | None, str, int | None, dict]]:
    """(label, checkpoint, controller, n_action_steps override, policy config overrides)."""
    adv = {"escape_advantage": args.escape_advantage}
    no_adv = {"escape_advantage": None}  # escape manoeuvres only when no sampled chunk is safe
    blend = {"blend_steps": args.blend_steps}
    rows = [
        ("PAC", None, "pac", None, {}),
        ("MPPI", None, "mppi", None, {}),
        ("route pursuit", None, "route-pursuit", None, {}),
    ]
    if args.old:
        rows += [("old default, standard", args.old, "diffusion", None, {})]
    for tag, path in (("new", args.new), ("new + DAgger", args.dagger), ("route", args.route)):
        if not path:
            continue
        rows += [
            (f"{tag}, standard", path, "diffusion", None, {}),
            (f"{tag}, best-of-{args.candidates}", path, "diffusion-bestof", None, no_adv),
            (f"{tag}, best-of-{args.candidates} + escapes", path, "diffusion-bestof", None, adv),
            (f"{tag}, CBF filter", path, "diffusion-cbf", None, {}),
            (f"{tag}, best-of-{args.candidates} + CBF", path, "diffusion-safe", None, no_adv),
            (f"{tag}, best-of-{args.candidates} + CBF + escapes", path, "diffusion-safe", None, adv),
        ]
        if args.blend_steps:
            rows += [
                (f"{tag}, standard + blending", path, "diffusion", None, blend),
                (
                    f"{tag}, best-of-{args.candidates} + escapes + blending",
                    path,
                    "diffusion-bestof",
                    None,
                    {**adv, **blend},
                ),
                (
                    f"{tag}, best-of-{args.candidates} + CBF + escapes + blending",
                    path,
                    "diffusion-safe",
                    None,
                    {**adv, **blend},
                ),
                (
                    f"{tag}, best-of-{args.candidates} + escapes + blending + stop",
                    path,
                    "diffusion-bestof",
                    None,
                    {**adv, **blend, "blocked_fallback": "stop"},
                ),
            ]
        if args.warm_start_step:
            warm = {**blend, "warm_start_step": args.warm_start_step}
            ws = " + blending + warm start" if args.blend_steps else " + warm start"
            k = args.candidates
            rows += [
                (f"{tag}, standard{ws}", path, "diffusion", None, warm),
                (f"{tag}, best-of-{k}{ws}", path, "diffusion-bestof", None, {**no_adv, **warm}),
                (f"{tag}, best-of-{k} + escapes{ws}", path, "diffusion-bestof", None, {**adv, **warm}),
                (f"{tag}, best-of-{k} + CBF{ws}", path, "diffusion-safe", None, {**no_adv, **warm}),
            ]
    if args.n_action_steps:
        best = args.dagger or args.new
        tag = "new + DAgger" if args.dagger else "new"
        rows += [
            (
                f"{tag}, standard, {args.n_action_steps} actions per replan",
                best,
                "diffusion",
                args.n_action_steps,
                {},
            ),
            (
                f"{tag}, both, {args.n_action_steps} actions per replan",
                best,
                "diffusion-safe",
                args.n_action_steps,
                no_adv,
            ),
            (
                f"{tag}, both + escapes, {args.n_action_steps} actions per replan",
                best,
                "diffusion-safe",
                args.n_action_steps,
                adv,
            ),
        ]
    return rows


def scene_set_runs(sets: list[str], seed: int, flags: Conditions) -> dict[str, tuple[Scenes, Conditions]]:
    """Each scene set's scenes (from first seed ``seed``) and the conditions it runs under: a level's
    own, else ``flags``; ValueError for a bad set or flags given with a level."""
    return {s: (parse_scenes(s, seed), scene_set_conditions(s, flags)) for s in sets}


def _mean(entry: dict, key: str, digits: int = 3) -> str:
    m = entry.get(key) or {}
    return "—" if m.get("mean") is None else f"{m['mean']:.{digits}g}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    ap.add_argument("--new", required=True, help="checkpoint of the new model")
    ap.add_argument("--old", default=None, help="checkpoint of the previous default")
    ap.add_argument("--dagger", default=None, help="checkpoint after a DAgger round")
    ap.add_argument("--route", default=None, help='a "nearest+route" checkpoint (the route-hint rows)')
    ap.add_argument("--sets", default="random:100,hard:100", help="comma-separated scene sets")
    ap.add_argument("--seed", type=int, default=UNSEEN_SEED_START)
    ap.add_argument("--candidates", type=int, default=10)
    ap.add_argument(
        "--escape-advantage",
        type=float,
        default=0.1,
        help="escape_advantage [m] of the '+ escapes' rows (ReplanExperiment)",
    )
    ap.add_argument(
        "--blend-steps",
        type=int,
        default=4,
        help="blend_steps of the '+ blending' rows (ReplanExperiment; 0: no such rows)",
    )
    ap.add_argument(
        "--num-inference-steps",
        type=int,
        default=None,
        help="DDIM steps of every diffusion row (default: each checkpoint's own num_inference_steps)",
    )
    ap.add_argument(
        "--warm-start-step",
        type=int,
        default=0,
        help="warm_start_step of the '+ warm start' rows (policy config field; 0: no such rows)",
    )
    ap.add_argument("--n-action-steps", type=int, default=None)
    ap.add_argument("--rows", default=None, help="only these rows: exact labels separated by ';'")
    ap.add_argument("--out", default="outputs/ablation")
    add_condition_arguments(ap)
    args = ap.parse_args(argv)
    sets = [s for s in args.sets.split(",") if s]
    try:
        runs = scene_set_runs(sets, args.seed, conditions_from_flags(args))
    except ValueError as e:
        ap.error(str(e).replace("conditions: ", "--env."))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    params = FormationParams()
    from lerobot_formation.policy.checkpoint import load_policy

    bundles: dict[str, tuple] = {}
    results: dict[str, dict] = {}
    rows = row_specs(args)
    if args.rows:
        keep = {k.strip() for k in args.rows.split(";")}
        rows = [r for r in rows if r[0] in keep]
    for label, path, name, n_act, overrides in rows:
        results[label] = {}
        bundle = None
        if path:
            if path not in bundles:
                bundles[path] = load_policy(path)
            bundle = bundles[path]
        # rows without "blending", "stop", "escapes" or "warm start" run without them
        settings = {
            "warm_start_step": 0,
            # a training-window field derived from n_action_steps: derived again (None)
            **({"n_action_steps": n_act, "drop_n_last_frames": None} if n_act else {}),
            **overrides,
        }
        experiment = ReplanExperiment(**{k: v for k, v in settings.items() if k in EXPERIMENT_FIELDS})
        options = ControllerOptions(
            policy_path=path,
            candidates=args.candidates,
            num_inference_steps=args.num_inference_steps,
            overrides={k: v for k, v in settings.items() if k not in EXPERIMENT_FIELDS},
            experiment=experiment,
        )
        for s in sets:
            sc, conditions = runs[s]
            # as in the bench: the safety layer knows this set's conditions and whether its obstacles move
            moving = sc.velocities is not None and bool(np.any(sc.velocities))
            set_options = dataclasses.replace(options, conditions=conditions, scenes_move=moving)
            t0 = time.perf_counter()
            try:
                ctrl = make_controller(name, params, set_options, bundle)
                rec = evaluate(ctrl, sc, params, progress=False, conditions=conditions)
            except ValueError as e:  # e.g. more obstacles than a "grid+list" policy can observe
                results[label][s] = {"error": str(e).split(";")[0]}
                print(f"[{s}] {label}: cannot run: {e}", flush=True)
                continue
            entry = controller_results(rec, sc)
            entry.pop("episodes")
            entry["wall_time_s"] = time.perf_counter() - t0
            if getattr(ctrl, "stats", None):
                entry.update(safety_rates(ctrl.stats))  # escape_rate and stop_rate included
            results[label][s] = entry
            lo, hi = entry["success_ci95"]
            print(
                f"[{s}] {label}: {entry['success_rate']:.0%} [{lo:.0%}, {hi:.0%}], collisions {entry['collisions']}, "
                f"timeouts {entry['timeouts']}, {entry['wall_time_s']:.0f} s",
                flush=True,
            )
    (out / "ablation.json").write_text(json.dumps(results, indent=1))
    lines = []
    for s in sets:
        changed = runs[s][1].changed()
        lines += [
            f"#### {s} (seeds from {args.seed}; conditions: {changed or 'none'})",
            "",
            "| controller | success % [95 % CI] | collisions | timeouts | smoothness | jerk | path (m) | time (s) "
            "| filter interventions | replans with no safe candidate | replans with an escape manoeuvre "
            "| replans that stop |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for label in results:
            e = results[label].get(s, {})
            if "error" in e:
                lines.append(f"| {label} | cannot run: {e['error']} | | | | | | | | | | |")
                continue
            lo, hi = e["success_ci95"]
            name = next(r[2] for r in rows if r[0] == label)
            fi = e.get("filter_intervention_rate") if name in ("diffusion-cbf", "diffusion-safe") else None
            ns = e.get("replans_none_safe_rate") if name in ("diffusion-bestof", "diffusion-safe") else None
            er = e.get("escape_rate") if name in ("diffusion-bestof", "diffusion-safe") else None
            sr = e.get("stop_rate") if name in ("diffusion-bestof", "diffusion-safe") else None
            lines.append(
                f"| {label} | {100 * e['success_rate']:.0f} [{100 * lo:.0f}, {100 * hi:.0f}] | {e['collisions']} | "
                f"{e['timeouts']} | {_mean(e, 'control_smoothness')} | {_mean(e, 'jerk')} | "
                f"{_mean(e, 'path_length')} | {_mean(e, 'time')} | "
                f"{'—' if fi is None else f'{100 * fi:.1f} %'} | {'—' if ns is None else f'{100 * ns:.1f} %'} | "
                f"{'—' if er is None else f'{100 * er:.1f} %'} | {'—' if sr is None else f'{100 * sr:.1f} %'} |"
            )
        lines.append("")
    (out / "ablation.md").write_text("\n".join(lines))
    print("\n".join(lines))
    print(f"wrote {out / 'ablation.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
