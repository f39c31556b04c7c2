"""Success rate against DDIM inference steps, on several scene sets in one run.

One checkpoint (``--policy.path``, default pretrained/formation_diffusion_route_v1) is loaded once; for each
step count of ``--steps`` (default 1,2,3,5,10) a controller (``--controller``, default the standard
"diffusion"; any diffusion controller of ``lerobot-formation-bench``, e.g. "diffusion-bestof") is
made with ``controllers.make_controller`` (``num_inference_steps`` = that count: DDIM on the training betas,
``diffusion_controller.set_inference_steps``) and run by the batched engine (``evaluation.evaluate``)
on every scene set of ``--scenes`` (default ``dataset:100``, the first 100 episodes of the training
data, from the checkpoint's dataset_scenes.json, and ``random:100``, unseen scenes of seeds from
``--seed`` = core.world.sampling.UNSEEN_SEED_START). Success is ``bench_results.controller_results``' success rate
with its Wilson 95 % interval. The policy's noise is seeded (``--seed-policy``), so every setting
sees the same scenes and the same first noise draw.

Time per replan: the wall time of each ``evaluate`` call divided by the controller's
``stats['replans']`` (episode replans: one chunk for one episode; the engine batches the live
episodes into one policy call, whose count is printed too), summed over the scene sets. It includes
the simulation and the observation encoding between replans, so it is the cost of a replan as the
evaluation pays it, not the bare sampler's latency (benchmarks/bench_replan_latency.py measures that).
A controller without ``stats['replans']`` is reported in total wall seconds.

"Within noise of 10 steps": a setting whose success count is not distinguishable from the reference
setting's (``--reference`` steps, default 10, spaced "leading" as the policy samples) on any scene
set by a pooled two-proportion z-test at 5 % (|z| < 1.96; ``same_rate``). Of those, the one with the
lowest time per replan is marked and is the headline, with its time per replan against the reference's.

Samplers: every step count of ``--steps`` runs with every DDIM timestep spacing of ``--spacings``
(diffusers' ``timestep_spacing``; default "leading", diffusers' and so LeRobot's and the policy's:
0, T/S, 2T/S, ...; "trailing" starts the first step at the last training timestep T - 1, which 1-3
step sampling needs, Lin et al. 2024; this script sets it on the scheduler, ``use_spacing``: the
policy has no such setting), all in one run.

Options: ``--n-action-steps N`` executes N actions per replan instead of the checkpoint's;
``--inference-backend eager|lean|trace`` sets the loaded policy config's ``inference_backend``
(default: the checkpoint's); ``--out FILE.json`` writes every number.

Run (full size; about 10 evaluations of 100 episodes: tens of minutes on 2 cores)::

    HF_HUB_OFFLINE=1 OMP_NUM_THREADS=1 python benchmarks/bench_sampling_steps.py \\
        --policy.path pretrained/formation_diffusion_route_v1 --threads 1 --out outputs/results/sampling_steps.json

``--quick`` is a smoke run: ``--scenes dataset:3,random:3 --steps 1,10``. The last line is the headline:
``fastest sampler within noise of DDIM 10 leading: <sampler> (success a % vs b % on <set>, ...; time per
replan x ms vs y ms, ratio r)``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")

from lerobot_formation.threads import add_threads_argument, apply_threads  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEFAULT_POLICY = REPO / "pretrained" / "formation_diffusion_route_v1"
BACKENDS = ("eager", "lean", "trace")  # configuration_formation_diffusion.INFERENCE_BACKENDS
SPACINGS = ("leading", "trailing", "linspace")  # diffusers' DDIMScheduler timestep_spacing


def use_spacing(policy, spacing: str) -> None:
    """Give the policy's diffusion models' schedulers the DDIM ``timestep_spacing`` ``spacing`` (the
    policy samples with the scheduler it holds; ``set_inference_steps`` builds one spaced "leading")."""
    for model in (policy.diffusion, getattr(policy, "ema_diffusion", None)):
        if model is None:
            continue
        scheduler = model.noise_scheduler
        if getattr(scheduler.config, "timestep_spacing", None) != spacing:
            model.noise_scheduler = type(scheduler).from_config(scheduler.config, timestep_spacing=spacing)


def int_list(text: str) -> list[int]:
    """'1,2,3' -> [1, 2, 3] (whole numbers >= 1, duplicates dropped, order kept)."""
    out: list[int] = []
    for item in (t.strip() for t in text.split(",") if t.strip()):
        try:
            n = int(item)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected comma-separated whole numbers, got {item!r}"
            ) from None
        if n < 1:
            raise argparse.ArgumentTypeError(f"steps must be >= 1, got {n}")
        if n not in out:
            out.append(n)
    if not out:
        raise argparse.ArgumentTypeError("expected at least one step count")
    return out


def same_rate(x1: int, n1: int, x2: int, n2: int, z_crit: float = 1.96) -> bool:
    """Whether two success counts x1/n1 and x2/n2 are within sampling noise of each other: the pooled
    two-proportion z-test does not reject equal rates at 5 % (two-sided, |z| < 1.96)."""
    from lerobot_formation.core.episodes.metrics import two_proportion_z

    return abs(two_proportion_z(x1, n1, x2, n2)) < z_crit


def within_noise(results: dict[str, dict[str, dict]], reference: str) -> list[str]:
    """Settings whose success is within noise of the reference's (``same_rate``) on every scene set.
    ``results[setting][set]`` holds ``success_rate`` and ``n_episodes``."""
    ref = results[reference]

    def count(e):
        return round(e["success_rate"] * e["n_episodes"]), e["n_episodes"]

    return [k for k, sets in results.items() if all(same_rate(*count(sets[s]), *count(ref[s])) for s in ref)]


def seconds_per_replan(sets: dict[str, dict]) -> float | None:
    """Total evaluation wall time over total episode replans (None if a controller did not count)."""
    if any(e.get("replans") is None for e in sets.values()):
        return None
    replans = sum(e["replans"] for e in sets.values())
    return sum(e["wall_s"] for e in sets.values()) / max(replans, 1)


def main(argv: list[str] | None = None) -> int:
    from lerobot_formation.core.world.sampling import UNSEEN_SEED_START

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--policy.path",
        dest="policy_path",
        default=None,
        help="checkpoint folder (default: pretrained/formation_diffusion_route_v1 of this repository)",
    )
    ap.add_argument(
        "--steps",
        type=int_list,
        default=[1, 2, 3, 5, 10],
        help="DDIM step counts, comma-separated (default: 1,2,3,5,10)",
    )
    ap.add_argument(
        "--reference",
        type=int,
        default=10,
        help="the step count the others are compared with (added to --steps if missing)",
    )
    ap.add_argument(
        "--scenes",
        default="dataset:100,random:100",
        help="comma-separated scene sets: random:N, <preset>:N, hard:N, dataset:N or FILE.json (default: %(default)s)",
    )
    ap.add_argument(
        "--seed", type=int, default=UNSEEN_SEED_START, help="first seed of random:N and preset sets"
    )
    ap.add_argument(
        "--dataset.root",
        dest="dataset_root",
        default=None,
        help="dataset for dataset:N (default: the checkpoint's dataset_scenes.json)",
    )
    ap.add_argument(
        "--controller",
        default="diffusion",
        help="a diffusion controller of lerobot-formation-bench: diffusion, diffusion-bestof, "
        "diffusion-cbf, diffusion-safe, diffusion-policy (default: %(default)s)",
    )
    ap.add_argument(
        "--candidates", type=int, default=10, help="K of the best-of-K controllers (default: %(default)s)"
    )
    ap.add_argument(
        "--seed-policy", type=int, default=0, help="seed of the policy's noise (default: %(default)s)"
    )
    ap.add_argument(
        "--n-action-steps",
        type=int,
        default=None,
        help="actions executed per replan (default: the checkpoint's)",
    )
    ap.add_argument(
        "--inference-backend",
        choices=BACKENDS,
        default=None,
        help="the policy config's inference_backend (default: the checkpoint's)",
    )
    ap.add_argument(
        "--spacings",
        default=None,
        help="comma-separated DDIM timestep spacings to run every step count with: leading, trailing, "
        "linspace (default: leading, the policy's)",
    )
    ap.add_argument("--out", default=None, help="write every number to this JSON file")
    add_threads_argument(ap, "torch threads")
    ap.add_argument(
        "--quick", action="store_true", help="smoke run: --scenes dataset:3,random:3 --steps 1,10"
    )
    args = ap.parse_args(argv)
    args.policy_path = args.policy_path or str(DEFAULT_POLICY)
    if args.quick:
        args.scenes, args.steps = "dataset:3,random:3", [1, 10]
    if args.reference not in args.steps:
        args.steps.append(args.reference)
    args.steps.sort()
    if args.n_action_steps is not None and args.n_action_steps < 1:
        ap.error(f"--n-action-steps must be >= 1, got {args.n_action_steps}")
    if not args.controller.startswith("diffusion"):
        ap.error(f"--controller must be a diffusion controller, got {args.controller!r}")
    sets = [s.strip() for s in args.scenes.split(",") if s.strip()]
    if not sets:
        ap.error("--scenes is empty")

    import torch  # noqa: F401 (loaded before apply_threads sets its thread count)

    from lerobot_formation.bench.controllers import CONTROLLERS, make_controller
    from lerobot_formation.bench.evaluation import evaluate
    from lerobot_formation.bench.results import controller_results
    from lerobot_formation.bench.scene_sets import parse_scenes
    from lerobot_formation.bench.settings import ControllerOptions
    from lerobot_formation.core.world.dynamics import FormationParams
    from lerobot_formation.policy.checkpoint import load_policy

    if args.controller not in CONTROLLERS:
        ap.error(f"unknown controller {args.controller!r}; choose from {CONTROLLERS}")
    threads = apply_threads(args.threads)
    try:
        bundle = load_policy(args.policy_path)
        scenes = {s: parse_scenes(s, args.seed, args.dataset_root, args.policy_path) for s in sets}
    except ValueError as e:
        ap.error(str(e))
    cfg = bundle[0].config
    if max(args.steps) > cfg.num_train_timesteps:
        ap.error(f"--steps must be <= {cfg.num_train_timesteps} (the checkpoint's training steps)")
    spacings = [t.strip() for t in (args.spacings or "leading").split(",") if t.strip()]
    bad = [t for t in spacings if t not in SPACINGS]
    if bad or not spacings:
        ap.error(f"--spacings must name some of {SPACINGS}, got {args.spacings!r}")
    c = bundle[0].config
    if args.n_action_steps is not None:
        if args.n_action_steps > c.horizon - c.n_obs_steps + 1:
            ap.error(f"--n-action-steps must be <= {c.horizon - c.n_obs_steps + 1} for this checkpoint")
        c.n_action_steps = args.n_action_steps
    if args.inference_backend is not None:
        c.inference_backend = args.inference_backend
    own = (
        f"{cfg.noise_scheduler_type} {cfg.num_inference_steps or cfg.num_train_timesteps} steps, "
        f"warm start {getattr(cfg, 'warm_start_step', 0)}"
    )
    print(
        f"policy {args.policy_path} (own sampler {own}, {cfg.n_action_steps} actions per replan, inference_backend "
        f"{cfg.inference_backend!r}), controller {args.controller}; scenes "
        + ", ".join(f"{s} ({len(scenes[s])})" for s in sets)
        + f"; torch threads {threads}, {os.cpu_count()} CPUs",
        flush=True,
    )

    # (label, checkpoint, policy bundle, DDIM steps, timestep spacing); the reference is
    # --reference steps spaced "leading", as the policy samples.
    settings = [(f"DDIM {k} {sp}", args.policy_path, bundle, k, sp) for sp in spacings for k in args.steps]
    ref = f"DDIM {args.reference} leading"
    if ref not in {lab for lab, *_ in settings}:
        settings.append((ref, args.policy_path, bundle, args.reference, "leading"))

    params = FormationParams()
    results: dict[str, dict[str, dict]] = {}
    # the checkpoint's own warm start, restored per setting (a step count at or below it turns it off)
    warm = cfg.warm_start_step
    for label, path, bun, k, spacing in settings:
        bun[0].reconfigure(warm_start_step=warm)
        options = ControllerOptions(
            candidates=args.candidates, num_inference_steps=k, seed_policy=args.seed_policy, policy_path=path
        )
        results[label] = {}
        for s in sets:
            try:
                ctrl = make_controller(args.controller, params, options, bun)
            except ValueError as e:  # e.g. a safety-layer controller on a world-frame checkpoint
                ap.error(f"controller {args.controller}: {e}")
            use_spacing(bun[0], spacing)  # on the scheduler its step count was set on
            t0 = time.perf_counter()
            rec = evaluate(ctrl, scenes[s], params, progress=False)
            wall = time.perf_counter() - t0
            entry = controller_results(rec, scenes[s])
            stats = getattr(ctrl, "stats", None) or {}
            e = {
                "steps": k,
                "timestep_spacing": spacing,
                "policy_path": str(path),
                "success_rate": entry["success_rate"],
                "success_ci95": list(entry["success_ci95"]),
                "n_episodes": entry["n_episodes"],
                "collisions": entry["collisions"],
                "timeouts": entry["timeouts"],
                "wall_s": wall,
                "replans": stats.get("replans"),
            }
            results[label][s] = e
            lo, hi = e["success_ci95"]
            per = f", {1e3 * wall / e['replans']:.2f} ms per replan" if e["replans"] else ""
            print(
                f"[{s}] {label}: success {e['success_rate']:.0%} [{lo:.0%}, {hi:.0%}] of {e['n_episodes']} "
                f"(collisions {e['collisions']}, timeouts {e['timeouts']}) in {wall:.1f} s, {e['replans']} replans{per}",
                flush=True,
            )

    ok = within_noise(results, ref)
    per_replan = {lab: seconds_per_replan(results[lab]) for lab in results}
    timed_per_replan = all(v is not None for v in per_replan.values())

    def cost(lab):
        return per_replan[lab] if timed_per_replan else sum(e["wall_s"] for e in results[lab].values())

    best = min(ok, key=lambda lab: (cost(lab), results[lab][sets[0]]["steps"]))
    time_head = "time per replan (ms)" if timed_per_replan else "total wall time (s)"
    print()
    print(
        "| sampler | "
        + " | ".join(f"{s} success % [Wilson 95 %]" for s in sets)
        + f" | {time_head} | within noise of {ref} |"
    )
    print("|---" * (len(sets) + 3) + "|")
    for lab in results:
        cells = []
        for s in sets:
            e = results[lab][s]
            lo, hi = e["success_ci95"]
            cells.append(f"{100 * e['success_rate']:.0f} [{100 * lo:.0f}, {100 * hi:.0f}]")
        t = 1e3 * cost(lab) if timed_per_replan else cost(lab)
        mark = (
            "reference"
            if lab == ref
            else ("**yes, fastest**" if lab == best else ("yes" if lab in ok else "no"))
        )
        print(f"| {lab} | " + " | ".join(cells) + f" | {t:.2f} | {mark} |")
    print()

    ratio = cost(best) / cost(ref)
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "meta": {
                "policy_path": args.policy_path,
                "controller": args.controller,
                "candidates": args.candidates,
                "scenes": sets,
                "seed": args.seed,
                "seed_policy": args.seed_policy,
                "n_action_steps": cfg.n_action_steps,
                "inference_backend": cfg.inference_backend,
                "threads": threads,
                "reference": ref,
                "within_noise_rule": "pooled two-proportion z-test, |z| < 1.96 on every scene set",
                "date": time.strftime("%Y-%m-%d"),
            },
            "results": results,
            "seconds_per_replan": per_replan,
            "within_noise_of_reference": ok,
            "fastest_within_noise": best,
            "time_ratio_to_reference": ratio,
        }
        tmp = out.with_name(out.name + ".tmp")
        tmp.write_text(json.dumps(payload, indent=1))
        tmp.replace(out)
        print(f"wrote {out}")
    succ = ", ".join(
        f"{100 * results[best][s]['success_rate']:.0f} % vs {100 * results[ref][s]['success_rate']:.0f} % on {s}"
        for s in sets
    )
    unit = "time per replan" if timed_per_replan else "wall time"
    a, b = (1e3 * cost(best), 1e3 * cost(ref)) if timed_per_replan else (cost(best), cost(ref))
    u = "ms" if timed_per_replan else "s"
    print(
        f"fastest sampler within noise of {ref}: {best} (success {succ}; {unit} {a:.2f} {u} vs {b:.2f} {u}, "
        f"ratio {ratio:.2f})"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
