"""Success rate against DDIM inference steps, on several scene sets in one run.

One checkpoint (``--policy.path``, default pretrained/formation_diffusion_safe) is loaded once; for each
step count of ``--steps`` (default 1,2,3,5,10) a controller (``--controller``, default the standard
"diffusion"; any diffusion controller of ``lerobot-formation-bench``, e.g. "diffusion-bestof") is
made with ``controllers.make_controller`` (``num_inference_steps`` = that count: DDIM on the training betas,
``diffusion_controller.set_inference_steps``) and run by the batched engine (``evaluation.evaluate``)
on every scene set of ``--scenes`` (default ``dataset:100``, the first 100 episodes of the training
data, from the checkpoint's dataset_scenes.json, and ``random:100``, unseen scenes of seeds from
``--seed`` = core.scene.UNSEEN_SEED_START). Success is ``bench_results.controller_results``' success rate
with its Wilson 95 % interval. The policy's noise is seeded (``--seed-policy``), so every setting
sees the same scenes and the same first noise draw.

Time per replan: the wall time of each ``evaluate`` call divided by the controller's
``stats['replans']`` (episode replans: one chunk for one episode; the engine batches the live
episodes into one policy call, whose count is printed too), summed over the scene sets. It includes
the simulation and the observation encoding between replans, so it is the cost of a replan as the
evaluation pays it, not the bare sampler's latency (benchmarks/bench_replan_latency.py measures that).
A controller without ``stats['replans']`` is reported in total wall seconds.

"Within noise of 10 steps": a setting whose Wilson interval overlaps the reference setting's
(``--reference``, default 10) on every scene set. The fewest-steps such setting is marked in the table
and is the headline, with its time per replan against the reference's.

Options: ``--n-action-steps N`` executes N actions per replan instead of the checkpoint's;
``--inference-backend eager|lean|trace`` sets the loaded policy config's ``inference_backend``
(default: the checkpoint's); ``--out FILE.json`` writes every number.

Run (full size; about 10 evaluations of 100 episodes: tens of minutes on 2 cores)::

    HF_HUB_OFFLINE=1 OMP_NUM_THREADS=1 python benchmarks/bench_sampling_steps.py \\
        --policy.path pretrained/formation_diffusion_safe --threads 1 --out outputs/results/sampling_steps.json

``--quick`` is a smoke run: ``--scenes dataset:3,random:3 --steps 1,10``. The last line is the headline:
``fewest DDIM steps within noise of 10: K (success a % vs b % on <set>, ...; time per replan x ms vs y ms,
ratio r)``.
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
DEFAULT_POLICY = REPO / "pretrained" / "formation_diffusion_safe"
BACKENDS = ("eager", "lean", "trace")  # configuration_formation_diffusion.INFERENCE_BACKENDS


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


def overlaps(a: tuple[float, float], b: tuple[float, float]) -> bool:
    """Whether two intervals [lo, hi] overlap."""
    return a[0] <= b[1] and b[0] <= a[1]


def within_noise(results: dict[int, dict[str, dict]], reference: int) -> list[int]:
    """Step counts whose success interval overlaps the reference's on every scene set, fewest first.
    ``results[steps][set]`` holds ``success_ci95``."""
    ref = results[reference]
    return sorted(
        k
        for k, sets in results.items()
        if all(overlaps(sets[s]["success_ci95"], ref[s]["success_ci95"]) for s in ref)
    )


def seconds_per_replan(sets: dict[str, dict]) -> float | None:
    """Total evaluation wall time over total episode replans (None if a controller did not count)."""
    if any(e.get("replans") is None for e in sets.values()):
        return None
    replans = sum(e["replans"] for e in sets.values())
    return sum(e["wall_s"] for e in sets.values()) / max(replans, 1)


def main(argv: list[str] | None = None) -> int:
    from lerobot_formation.core.scene import UNSEEN_SEED_START

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--policy.path",
        dest="policy_path",
        default=None,
        help="checkpoint folder (default: pretrained/formation_diffusion_safe of this repository)",
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
        help="a diffusion controller of lerobot-formation-bench: diffusion, diffusion-bestof, diffusion-adaptive, "
        "diffusion-cbf, diffusion-safe (default: %(default)s)",
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

    from lerobot_formation.bench_results import controller_results
    from lerobot_formation.controllers import CONTROLLERS, make_controller
    from lerobot_formation.core.dynamics import FormationParams
    from lerobot_formation.diffusion_controller import load_policy
    from lerobot_formation.evaluation import evaluate
    from lerobot_formation.scene_sets import parse_scenes

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
    if args.n_action_steps is not None:
        if args.n_action_steps > cfg.horizon - cfg.n_obs_steps + 1:
            ap.error(f"--n-action-steps must be <= {cfg.horizon - cfg.n_obs_steps + 1} for this checkpoint")
        cfg.n_action_steps = args.n_action_steps
    if args.inference_backend is not None:
        cfg.inference_backend = args.inference_backend
    own = f"{cfg.noise_scheduler_type} {cfg.num_inference_steps or cfg.num_train_timesteps} steps"
    print(
        f"policy {args.policy_path} (own sampler {own}, {cfg.n_action_steps} actions per replan, inference_backend "
        f"{cfg.inference_backend!r}), controller {args.controller}; scenes "
        + ", ".join(f"{s} ({len(scenes[s])})" for s in sets)
        + f"; torch threads {threads}, {os.cpu_count()} CPUs",
        flush=True,
    )

    params = FormationParams()
    bench_args = argparse.Namespace(
        candidates=args.candidates,
        num_inference_steps=None,
        seed_policy=args.seed_policy,
        policy_path=args.policy_path,
    )
    results: dict[int, dict[str, dict]] = {}
    for k in args.steps:
        bench_args.num_inference_steps = k
        results[k] = {}
        for s in sets:
            try:
                ctrl = make_controller(args.controller, params, bench_args, bundle)
            except ValueError as e:  # e.g. a safety-layer controller on a world-frame checkpoint
                ap.error(f"controller {args.controller}: {e}")
            t0 = time.perf_counter()
            rec = evaluate(ctrl, scenes[s], params, progress=False)
            wall = time.perf_counter() - t0
            entry = controller_results(rec, scenes[s])
            stats = getattr(ctrl, "stats", None) or {}
            e = {
                "success_rate": entry["success_rate"],
                "success_ci95": list(entry["success_ci95"]),
                "n_episodes": entry["n_episodes"],
                "collisions": entry["collisions"],
                "timeouts": entry["timeouts"],
                "wall_s": wall,
                "replans": stats.get("replans"),
                "policy_calls": getattr(ctrl, "replans", None),
            }
            results[k][s] = e
            lo, hi = e["success_ci95"]
            per = f", {1e3 * wall / e['replans']:.2f} ms per replan" if e["replans"] else ""
            print(
                f"[{s}] DDIM {k:>3} steps: success {e['success_rate']:.0%} [{lo:.0%}, {hi:.0%}] of {e['n_episodes']} "
                f"(collisions {e['collisions']}, timeouts {e['timeouts']}) in {wall:.1f} s, {e['replans']} replans "
                f"in {e['policy_calls']} batched calls{per}",
                flush=True,
            )

    ref = args.reference
    ok = within_noise(results, ref)
    best = ok[0]
    per_replan = {k: seconds_per_replan(results[k]) for k in args.steps}
    timed_per_replan = all(v is not None for v in per_replan.values())
    time_head = "time per replan (ms)" if timed_per_replan else "total wall time (s)"
    print()
    print(
        "| DDIM steps | "
        + " | ".join(f"{s} success % [Wilson 95 %]" for s in sets)
        + f" | {time_head} | within noise of {ref} steps |"
    )
    print("|---" * (len(sets) + 3) + "|")
    for k in args.steps:
        cells = []
        for s in sets:
            e = results[k][s]
            lo, hi = e["success_ci95"]
            cells.append(f"{100 * e['success_rate']:.0f} [{100 * lo:.0f}, {100 * hi:.0f}]")
        t = 1e3 * per_replan[k] if timed_per_replan else sum(e["wall_s"] for e in results[k].values())
        mark = (
            "reference"
            if k == ref
            else ("**yes, fewest steps**" if k == best else ("yes" if k in ok else "no"))
        )
        print(f"| {k} | " + " | ".join(cells) + f" | {t:.2f} | {mark} |")
    print()

    def cost(k):
        return per_replan[k] if timed_per_replan else sum(e["wall_s"] for e in results[k].values())

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
                "date": time.strftime("%Y-%m-%d"),
            },
            "results": {str(k): v for k, v in results.items()},
            "seconds_per_replan": {str(k): v for k, v in per_replan.items()},
            "within_noise_of_reference": ok,
            "fewest_within_noise": best,
            "time_ratio_to_reference": ratio,
        }
        out.write_text(json.dumps(payload, indent=1))
        print(f"wrote {out}")
    succ = ", ".join(
        f"{100 * results[best][s]['success_rate']:.0f} % vs {100 * results[ref][s]['success_rate']:.0f} % on {s}"
        for s in sets
    )
    unit = "time per replan" if timed_per_replan else "wall time"
    a, b = (1e3 * cost(best), 1e3 * cost(ref)) if timed_per_replan else (cost(best), cost(ref))
    u = "ms" if timed_per_replan else "s"
    print(
        f"fewest DDIM steps within noise of {ref}: {best} (success {succ}; {unit} {a:.2f} {u} vs {b:.2f} {u}, "
        f"ratio {ratio:.2f})"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
