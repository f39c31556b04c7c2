"""Replan latency (issue 5, benchmark 2).

(a) The paper-size network (``configs/formation_diffusion_paper.json``: U-Net down dims
    [256, 512, 1024], step embedding 256, horizon 64, DDPM with 100 steps), built untrained from the
    config with the checkpoint's processors: one replan through LeRobot's stock ``select_action``
    for one episode (``reset()`` then ``select_action``: an empty action queue, so one full
    ``generate_actions``), against our fastest setting: DDIM with ``--ddim-steps`` steps
    (``diffusion_controller.set_inference_steps``), batched over ``--batch`` episodes in one
    ``DiffusionController.plan`` call, per episode. Which step count keeps the paper's success is
    measured by the success-against-steps table; pass that count as ``--ddim-steps``.
(b) The default model's latency (``--policy.path``, its own sampler): one ``DiffusionController.plan``
    for one episode, per episode for ``--batch`` episodes, and the stock ``select_action`` for one.

Timings are medians over ``--repeats`` calls after a warm-up call, with ``--threads`` torch threads.

Run (full size)::

    HF_HUB_OFFLINE=1 OMP_NUM_THREADS=1 python benchmarks/bench_replan_latency.py \\
        --policy.path pretrained/<name> --threads 1
    HF_HUB_OFFLINE=1 OMP_NUM_THREADS=2 python benchmarks/bench_replan_latency.py \\
        --policy.path pretrained/<name> --threads 2

``--quick``: one repeat, batch 10. The last line is the ratio of (a): stock DDPM-100 select_action
over our batched DDIM per episode.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def timed(fn, repeats: int) -> float:
    """Median seconds of fn() over repeats calls, after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def paper_policy(config_path: Path):
    """Untrained paper-size FormationDiffusionPolicy and processors (synthetic normalisation stats)."""
    import draccus
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

    from lerobot_formation.configuration_formation_diffusion import FormationDiffusionConfig
    from lerobot_formation.core.obstacle_grid import environment_state_dim
    from lerobot_formation.modeling_formation_diffusion import FormationDiffusionPolicy

    raw = json.loads(config_path.read_text())
    fields = {k: v for k, v in raw["policy"].items() if k != "type"}
    fields["device"] = "cpu"
    cfg = draccus.decode(FormationDiffusionConfig, fields)
    env_dim = environment_state_dim(raw.get("env", {}).get("obstacle_encoding", "grid"))
    cfg.input_features = {
        OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(7,)),
        OBS_ENV_STATE: PolicyFeature(type=FeatureType.ENV, shape=(env_dim,)),
    }
    cfg.output_features = {ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(2,))}
    policy = FormationDiffusionPolicy(cfg)
    policy.eval()

    def stats(lo, hi):
        lo, hi = np.asarray(lo, np.float32), np.asarray(hi, np.float32)
        return {"min": lo, "max": hi, "mean": (lo + hi) / 2, "std": (hi - lo) / 4}

    dataset_stats = {
        OBS_STATE: stats([-1, -1, -1, -1, -0.6, -0.6, -1.5], [7, 7, 1, 1, 0.6, 0.6, 1.5]),
        ACTION: stats([0, -1.5], [0.6, 1.5]),
    }
    pre, post = make_pre_post_processors(cfg, dataset_stats=dataset_stats)
    return policy, pre, post


def stock_replan_s(policy, pre, post, env_dim: int, repeats: int) -> float:
    """One replan through the stock select_action for one episode (empty queue -> generate_actions)."""
    g = torch.Generator().manual_seed(0)
    obs = {
        "observation.state": torch.randn(1, 7, generator=g),
        "observation.environment_state": torch.rand(1, env_dim, generator=g),
    }

    @torch.no_grad()
    def replan():
        policy.reset()
        post(policy.select_action(pre(dict(obs))))

    return timed(replan, repeats)


def engine_replan_s(ctrl, n: int, repeats: int) -> float:
    """One batched DiffusionController.plan for n episodes (seconds for the whole call)."""
    from lerobot_formation.core.scene import UNSEEN_SEED_START, sample_scenes

    scenes = sample_scenes(UNSEEN_SEED_START + np.arange(n))
    ctrl.reset(scenes)
    idx = np.arange(n)
    return timed(lambda: ctrl.plan(idx, scenes.start), repeats)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--policy.path", dest="policy_path", default=None, help="default model (part b)")
    ap.add_argument("--paper-config", default=str(REPO / "configs" / "formation_diffusion_paper.json"))
    ap.add_argument("--ddim-steps", type=int, default=10, help="our fastest setting's DDIM steps (part a)")
    ap.add_argument("--batch", type=int, default=100, help="episodes per batched replan")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: OMP_NUM_THREADS)")
    ap.add_argument("--quick", action="store_true", help="smoke run: 1 repeat, batch 10")
    args = ap.parse_args(argv)
    if args.quick:
        args.repeats, args.batch = 1, min(args.batch, 10)
    if args.threads:
        torch.set_num_threads(args.threads)
    threads = torch.get_num_threads()

    from lerobot_formation.diffusion_controller import DiffusionController, load_policy

    print(
        f"torch threads {threads}, {os.cpu_count()} CPUs; median of {args.repeats} after a warm-up",
        flush=True,
    )

    # (b) The default model.
    if args.policy_path:
        bundle = load_policy(args.policy_path)
        cfg = bundle[0].config
        env_dim = cfg.input_features["observation.environment_state"].shape[0]
        sampler = f"{cfg.noise_scheduler_type} {cfg.num_inference_steps or cfg.num_train_timesteps} steps"
        ctrl = DiffusionController(args.policy_path, policy_bundle=bundle)
        one = engine_replan_s(ctrl, 1, args.repeats)
        many = engine_replan_s(ctrl, args.batch, args.repeats)
        stock = stock_replan_s(*bundle, env_dim, args.repeats)
        print(
            f"(b) default model {args.policy_path} (down_dims {list(cfg.down_dims)}, horizon {cfg.horizon}, "
            f"{sampler}):"
        )
        print(f"    engine plan, 1 episode: {1e3 * one:.1f} ms per replan")
        print(
            f"    engine plan, {args.batch} episodes: {1e3 * many / args.batch:.2f} ms per episode ({1e3 * many:.0f} ms per call)"
        )
        print(f"    stock select_action, 1 episode: {1e3 * stock:.1f} ms per replan")

    # (a) The paper-size network.
    policy, pre, post = paper_policy(Path(args.paper_config))
    cfg = policy.config
    env_dim = cfg.input_features["observation.environment_state"].shape[0]
    n_params = sum(p.numel() for p in policy.diffusion.parameters())
    stock = stock_replan_s(policy, pre, post, env_dim, args.repeats)
    ctrl = DiffusionController(None, num_inference_steps=args.ddim_steps, policy_bundle=(policy, pre, post))
    one = engine_replan_s(ctrl, 1, args.repeats)
    many = engine_replan_s(ctrl, args.batch, args.repeats)
    ours = many / args.batch
    print(
        f"(a) paper-size network (down_dims {list(cfg.down_dims)}, step embed {cfg.diffusion_step_embed_dim}, "
        f"horizon {cfg.horizon}, {n_params / 1e6:.1f} M parameters, untrained):"
    )
    print(
        f"    stock select_action, DDPM {cfg.num_inference_steps or cfg.num_train_timesteps} steps, 1 episode: {1e3 * stock:.0f} ms per replan"
    )
    print(f"    engine plan, DDIM {args.ddim_steps} steps, 1 episode: {1e3 * one:.0f} ms per replan")
    print(
        f"    engine plan, DDIM {args.ddim_steps} steps, {args.batch} episodes: {1e3 * ours:.1f} ms per episode "
        f"({1e3 * many:.0f} ms per call)"
    )
    print(
        f"ratio stock DDPM select_action / engine batched DDIM-{args.ddim_steps} per episode: {stock / ours:.0f}x"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
