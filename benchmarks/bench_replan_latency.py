"""Replan latency (issue 5, benchmark 2).

(a) The paper-size network (``configs/formation_diffusion_paper.json``: U-Net down dims
    [256, 512, 1024], step embedding 256, horizon 64, DDPM with 100 steps), built untrained from the
    config with the checkpoint's processors: one replan through LeRobot's stock ``select_action``
    for one episode (``reset()`` then ``select_action``: an empty action queue, so one full
    ``generate_actions``), against our fastest setting: DDIM with ``--ddim-steps`` steps
    (``diffusion_controller.set_inference_steps``), batched over ``--batch`` episodes in one
    first ``DiffusionController.act`` call (every episode replans), per episode. Which step count keeps the paper's success is
    measured by the success-against-steps table; pass that count as ``--ddim-steps``.
(b) The default model's latency (``--policy.path``, its own sampler): one engine replan (the first
    ``DiffusionController.act`` after ``reset``) for one episode, per episode for ``--batch`` episodes, and the stock ``select_action`` for one.
(c) The lean inference path (policy config ``inference_backend``) on the default model
    (``--policy.path``, else pretrained/formation_diffusion_route_v1): one replan for one observation (B=1),
    i.e. one ``sample_action_chunks`` call (conditioning + the K candidates' batched denoising, what
    ``select_action``, the safety layer and the engine run), for K in ``--lean-candidates`` and DDIM
    steps in ``--lean-steps``, each change added in turn: the eager baseline (LeRobot's
    ``conditional_sample`` under ``torch.no_grad``, as the stock ``predict_action_chunk``), then
    ``torch.inference_mode``, then precomputed DDIM steps (backend "lean"), then the traced and frozen
    U-Net (backend "trace"); the variants are timed in turn, ``--lean-repeats`` rounds (medians). Also
    one U-Net call, eager against traced, and the largest difference of the sampled chunks (same
    noise) from the eager ones. ``--parts c`` runs only this part (well under 2 minutes).

Timings are medians over ``--repeats`` calls after a warm-up call, with ``--threads`` torch threads.

Run (full size)::

    HF_HUB_OFFLINE=1 OMP_NUM_THREADS=1 python benchmarks/bench_replan_latency.py \\
        --policy.path pretrained/<name> --threads 1
    HF_HUB_OFFLINE=1 OMP_NUM_THREADS=2 python benchmarks/bench_replan_latency.py \\
        --policy.path pretrained/<name> --threads 2

    HF_HUB_OFFLINE=1 OMP_NUM_THREADS=1 python benchmarks/bench_replan_latency.py --parts c --threads 1

(e) The safety layer (``--parts e``): every replan at B=1 through ``select_action`` over whole episodes
    of ``--safety-scenes`` unseen paper scenes, K = 1 and K = max(``--lean-candidates``) (best-of-K),
    the scorer's cost-to-go against its whole-field baseline on the same calls (``replay_scorer``: the
    calls of a best-of-K run recorded, then each timed with both, interleaved), the policy's traced
    U-Net against a plain trace of LeRobot's (``plain_trace``) in the same run. Its headline is the
    last line
    when it runs. ``--level levelK``: the level's scenes (its first seeds) under its conditions instead,
    with the safety layer told the conditions as the bench tells it (``safety_settings``).

(f) Where that replan's time goes (``--parts f``): part (e)'s scenes (``--level`` as there) at K =
    max(``--lean-candidates``) with the checkpoint's config, each stage of ``select_action``'s
    replanner timed by patching its function for the run (``StageClock``): per replan step the
    sampling (the denoiser calls, the clearance guidance, the rest), best-of-K's scoring, and that
    step's safety view and recheck (their means over every step beside). Its last line gives the
    stages' sum against the measured mean replan step (their ratio): what a faster replan has to
    cut, e.g.::

        HF_HUB_OFFLINE=1 OMP_NUM_THREADS=1 python benchmarks/bench_replan_latency.py --parts f \
            --level level5 --safety-scenes 10 --threads 1

``--quick``: one repeat, batch 10 (and 5 rounds in (c)). The last line is the headline of (f) when it
runs, else of (e) when it runs, else of (c) when it
runs (``replan latency B=1 K=1: ...``: the trace backend against the eager baseline at the first of
``--lean-steps``), else the ratio of (a): stock DDPM-100 select_action over our batched DDIM per episode.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from lerobot_formation.bench.timing import median_seconds  # noqa: E402
from lerobot_formation.threads import add_threads_argument, apply_threads  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def paper_policy(config_path: Path):
    """Untrained paper-size FormationDiffusionPolicy and processors (synthetic normalisation stats)."""
    import draccus
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

    from lerobot_formation.core.encodings.obstacle_grid import environment_state_dim
    from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig
    from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy

    raw = json.loads(config_path.read_text())
    fields = {k: v for k, v in raw["policy"].items() if k != "type"}
    fields["device"] = "cpu"
    env_dim = environment_state_dim(raw.get("env", {}).get("obstacle_encoding", "grid"))
    cfg = dataclasses.replace(
        draccus.decode(FormationDiffusionConfig, fields),
        input_features={
            OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(7,)),
            OBS_ENV_STATE: PolicyFeature(type=FeatureType.ENV, shape=(env_dim,)),
        },
        output_features={ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(2,))},
    )
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

    return median_seconds(replan, repeats)


def engine_replan_s(ctrl, n: int, repeats: int) -> float:
    """One batched engine replan for n episodes: ``reset`` then the first ``act`` (every episode
    replans), seconds for the whole call."""
    from lerobot_formation.core.world.dynamics import initial_state
    from lerobot_formation.core.world.sampling import UNSEEN_SEED_START, sample_scenes

    scenes = sample_scenes(UNSEEN_SEED_START + np.arange(n))
    from lerobot_formation.core.perception.conditions import Perception

    view = Perception.exact(scenes, initial_state(scenes.start, ctrl.params))  # what the engine passes
    idx = np.arange(n)

    def replan():
        ctrl.reset(view)
        ctrl.act(view, idx)

    return median_seconds(replan, repeats)


LEAN_VARIANTS = ("eager", "+inference_mode", "+DDIM precomputed", "+traced U-Net")


def lean_replan_ms(policy, candidates: int, repeats: int) -> dict[str, float]:
    """Median ms of one B=1 replan with K=candidates for each of LEAN_VARIANTS (timed in turn, after two
    warm-up calls each), and the largest chunk difference from eager ("max diff")."""
    from lerobot_formation.compat.lerobot_compat import global_conditioning

    cfg = policy.config
    env_dim = cfg.input_features["observation.environment_state"].shape[0]
    g = torch.Generator().manual_seed(0)
    batch = {
        "observation.state": torch.rand(1, cfg.n_obs_steps, 7, generator=g) * 2 - 1,
        "observation.environment_state": torch.rand(1, cfg.n_obs_steps, env_dim, generator=g),
    }
    noise = torch.randn(candidates, cfg.horizon, cfg.action_feature.shape[0], generator=g)
    model = policy.inference_model

    def stock():
        with torch.no_grad():
            cond = global_conditioning(model, batch).repeat_interleave(candidates, dim=0)
            return model.conditional_sample(candidates, global_cond=cond, noise=noise)[
                :, cfg.n_obs_steps - 1 :
            ]

    def backend(name):
        def run():
            policy.reconfigure(inference_backend=name)
            return policy.sample_action_chunks(batch, candidates, noise=noise)[0]

        return run

    calls = dict(
        zip(LEAN_VARIANTS, (stock, backend("eager"), backend("lean"), backend("trace")), strict=True)
    )
    times = {name: [] for name in calls}
    out = {}
    for name, fn in calls.items():
        out[name] = fn()
        fn()
    for _ in range(repeats):
        for name, fn in calls.items():
            t = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t)
    policy.reconfigure(inference_backend="eager")
    result = {name: 1e3 * statistics.median(times[name]) for name in calls}
    result["max diff"] = max(float((out[n] - out["eager"]).abs().max()) for n in calls)
    return result


def unet_call_ms(policy, repeats: int) -> tuple[float, float, float]:
    """Median ms of one U-Net call at B=1 (inference_mode): eager, traced + frozen; and the ms the
    trace took to build (trace, freeze, check)."""
    from lerobot_formation.compat.lerobot_compat import global_conditioning

    cfg = policy.config
    model = policy.inference_model
    env_dim = cfg.input_features["observation.environment_state"].shape[0]
    batch = {
        "observation.state": torch.zeros(1, cfg.n_obs_steps, 7),
        "observation.environment_state": torch.zeros(1, cfg.n_obs_steps, env_dim),
    }
    with torch.inference_mode():
        args = (torch.randn(1, cfg.horizon, 2), torch.full((1,), 10), global_conditioning(model, batch))
        t = time.perf_counter()
        traced = policy._lean.unet(model, model.unet, *args)
        build = time.perf_counter() - t
        if traced is model.unet:
            raise RuntimeError("tracing the U-Net failed (see the warning above)")
        times = ([], [])
        for _ in range(repeats):  # in turn, as the machine's load drifts
            for fn, out in zip((model.unet, traced), times, strict=True):
                t = time.perf_counter()
                fn(*args)
                out.append(time.perf_counter() - t)
        return 1e3 * statistics.median(times[0]), 1e3 * statistics.median(times[1]), 1e3 * build


def lean_part(path: str, candidates: list[int], steps: list[int], repeats: int) -> str:
    """Print part (c); return its headline (K=1 at steps[0], trace against eager)."""
    from lerobot_formation.policy.checkpoint import load_policy, set_inference_steps
    from lerobot_formation.policy.configuration_formation_diffusion import LAYER_OFF

    policy = load_policy(path)[0]
    # the sampler alone, unguided like the stock conditional_sample (guidance runs only in lean / trace)
    policy.reconfigure(**LAYER_OFF)
    cfg = policy.config
    print(
        f"(c) lean inference, {path} (down_dims {list(cfg.down_dims)}, horizon {cfg.horizon}, unguided), one replan "
        f"at B=1, median of {repeats} rounds; ms (speed-up over eager):"
    )
    eager_unet, traced_unet, build = unet_call_ms(policy, 10 * repeats)
    print(
        f"    one U-Net call: eager {eager_unet:.2f} ms, traced+frozen {traced_unet:.2f} ms "
        f"({eager_unet / traced_unet:.2f}x; built once in {build:.0f} ms on the first call)"
    )
    print("    " + "  ".join(f"{h:>17}" for h in ("K, DDIM steps", *LEAN_VARIANTS)) + "  max |diff|")
    headline = None
    for n in steps:
        set_inference_steps(policy, n)
        for k in candidates:
            r = lean_replan_ms(policy, k, repeats)
            eager = r["eager"]
            cells = [f"{k}, {n}", f"{eager:.2f}"] + [
                f"{r[v]:.2f} ({eager / r[v]:.2f}x)" for v in LEAN_VARIANTS[1:]
            ]
            print("    " + "  ".join(f"{c:>17}" for c in cells) + f"  {r['max diff']:.1e}")
            if headline is None and k == 1:
                trace = r[LEAN_VARIANTS[-1]]
                headline = (
                    f"replan latency B=1 K=1: {trace:.1f} ms (eager {eager:.1f} ms, ratio {eager / trace:.2f}x; "
                    f"inference_backend=trace, DDIM {n} steps, {torch.get_num_threads()} thread(s))"
                )
    return headline


def episode_replans_ms(
    policy,
    pre,
    post,
    encoding: str,
    seeds,
    scorer=None,
    env_kwargs: dict | None = None,
    plain_trace: bool = False,
) -> tuple[list[float], list]:
    """Run one B=1 episode per seed (unseen paper scenes) through ``FormationEnv`` and the policy's
    ``select_action`` (pre/post processors), as ``lerobot-eval`` steps it; return the duration [ms] of
    every call that replanned (sampled and, with K > 1, scored a new chunk) and the actions taken.
    ``scorer``: a replacement for ``core.safety.filters.cost_to_go_at`` (the baseline), else the shipped one.
    ``env_kwargs``: ``FormationEnv`` keyword arguments (a level's scenes and conditions). Torch's generator is seeded per episode, so two scorers that keep the same chunks take the same
    actions. ``plain_trace``: the policy's trace is a plain ``torch.jit.trace`` of LeRobot's U-Net, not
    of ``policy.unet_inference``'s copies."""
    from lerobot.envs.utils import preprocess_observation

    from lerobot_formation.core.safety import filters as safety
    from lerobot_formation.envs.env import FormationEnv
    from lerobot_formation.policy import modeling_formation_diffusion as modeling

    env = FormationEnv(**{**(env_kwargs or {}), "obstacle_encoding": encoding})
    shipped, copies = safety.cost_to_go_at, modeling.inference_copy
    safety.cost_to_go_at = scorer or shipped
    if plain_trace:  # traced again on its first call (in its mean, not its median), and after it
        modeling.inference_copy = lambda module, matmul_convolutions: module
        policy._lean.unets.clear()
    times, actions = [], []
    try:
        for seed in seeds:
            obs, _ = env.reset(seed=int(seed))
            policy.reset()
            torch.manual_seed(int(seed))
            done = False
            while not done:
                batch = pre(preprocess_observation({k: v[None] for k, v in obs.items()}))
                before = policy.safety_stats["replans"]
                t0 = time.perf_counter()
                with torch.inference_mode():
                    action = post(policy.select_action(batch))
                dt = time.perf_counter() - t0
                if policy.safety_stats["replans"] > before:
                    times.append(1e3 * dt)
                a = action[0].numpy()
                actions.append(a)
                obs, _, terminated, truncated, _ = env.step(a)
                done = terminated or truncated
    finally:
        safety.cost_to_go_at, modeling.inference_copy = shipped, copies
        if plain_trace:
            policy._lean.unets.clear()
    return times, actions


def layer_setup(path: str, scenes: int, level: str | None = None):
    """The checkpoint at ``path`` with the traced U-Net, and the scenes of parts (e) and (f):
    (policy, pre, post, seeds, env_kwargs, where). ``scenes`` unseen paper scenes, or with ``level``
    that level's first scenes under its conditions, the policy's safety layer told them as the bench
    tells it (``safety_settings``)."""
    from lerobot_formation.core.world.sampling import UNSEEN_SEED_START
    from lerobot_formation.policy.checkpoint import load_policy

    policy, pre, post = load_policy(path)
    policy.reconfigure(inference_backend="trace")
    seeds = UNSEEN_SEED_START + np.arange(scenes)
    env_kwargs, where = None, f"{scenes} unseen paper scenes"
    if level is not None:
        from lerobot_formation.bench.controllers import safety_settings
        from lerobot_formation.core.episodes.levels import get_level
        from lerobot_formation.envs.env_config import FormationEnvConfig

        env_cfg = FormationEnvConfig(level=level, obstacle_encoding=policy.config.obstacle_encoding)
        env_kwargs = {k_: v for k_, v in env_cfg.gym_kwargs.items() if k_ != "render_mode"}
        seeds = get_level(level).seed + np.arange(scenes)
        policy.reconfigure(**safety_settings(env_cfg.conditions()))
        where = f"{scenes} scenes of {level} under its conditions"
    return policy, pre, post, seeds, env_kwargs, where


class StageClock:
    """Wall time [s] and calls per stage of ``select_action``'s replanner, by patching the stages'
    functions for the duration of a ``with`` block (restored after): the step's safety view
    (``Replanner.view``) and recheck (``Replanner._recheck``), the K candidates' sampling
    (``sample_action_chunks``), inside it every denoiser call (the callable ``_LeanCache.unet``
    returns) and every clearance-guidance step (the closure ``Replanner._guide`` returns), and
    best-of-K's scoring (``Replanner.choose``). The view and the recheck run at every step; their time
    at the steps that replanned (``Replanner.act`` calls that added a replan) is kept apart
    (``at_replans``), so a replan step's stages add up to what that step ran."""

    PER_STEP = ("view", "recheck")

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self.at_replans: dict[str, float] = {}
        self._step: dict[str, float] = {}
        self._undo: list = []

    def _add(self, label: str, fn):
        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                dt = time.perf_counter() - t0
                self.seconds[label] = self.seconds.get(label, 0.0) + dt
                self.calls[label] = self.calls.get(label, 0) + 1
                self._step[label] = self._step.get(label, 0.0) + dt

        return timed

    def _act(self, real):
        def act(replanner, *args, **kwargs):
            self._step.clear()
            before = replanner.stats["replans"]
            out = real(replanner, *args, **kwargs)
            if replanner.stats["replans"] > before:
                for label in self.PER_STEP:
                    self.at_replans[label] = self.at_replans.get(label, 0.0) + self._step.get(label, 0.0)
            return out

        return act

    def _patch(self, owner, name: str, wrapper) -> None:
        real = owner.__dict__[name]  # the class's own function: restored as it was
        self._undo.append((owner, name, real))
        setattr(owner, name, wrapper(real))

    def __enter__(self):
        from lerobot_formation.policy import modeling_formation_diffusion as modeling
        from lerobot_formation.policy.replanner import Replanner

        for owner, name, label in (
            (Replanner, "view", "view"),
            (Replanner, "_recheck", "recheck"),
            (Replanner, "choose", "scoring"),
            (modeling.FormationDiffusionPolicy, "sample_action_chunks", "sampling"),
        ):
            self._patch(owner, name, lambda real, label=label: self._add(label, real))
        # the callables these return are what runs: time each call of them
        self._patch(
            modeling._LeanCache, "unet", lambda real: lambda *a, **k: self._add("U-Net", real(*a, **k))
        )
        self._patch(Replanner, "_guide", lambda real: lambda *a, **k: self._add("guidance", real(*a, **k)))
        self._patch(Replanner, "act", self._act)
        return self

    def __exit__(self, *exc):
        for owner, name, real in reversed(self._undo):
            setattr(owner, name, real)
        self._undo.clear()

    def clear(self) -> None:
        self.seconds.clear()
        self.calls.clear()
        self.at_replans.clear()


def stage_part(path: str, k: int, scenes: int, level: str | None = None) -> str:
    """Print part (f); return its headline: where a best-of-K replan's time goes, at B = 1 through
    ``select_action`` over whole episodes (``episode_replans_ms``, the checkpoint's config at K = k):
    per replan step the sampling (the denoiser calls, the clearance guidance, the rest: conditioning
    and DDIM arithmetic), best-of-K's scoring, and that step's safety view and recheck (``StageClock``;
    their means over every step beside). The stages' sum is printed beside the measured mean replan
    step, their ratio on the last line (what is left: the processors, the action queue, the filter)."""
    policy, pre, post, seeds, env_kwargs, where = layer_setup(path, scenes, level)
    policy.reconfigure(num_candidates=k)
    cfg = policy.config
    with StageClock() as clock:
        episode_replans_ms(policy, pre, post, cfg.obstacle_encoding, seeds[:1], None, env_kwargs)  # warm-up
        clock.clear()
        times, actions = episode_replans_ms(policy, pre, post, cfg.obstacle_encoding, seeds, None, env_kwargs)
    replans, steps = len(times), len(actions)
    sec, calls = clock.seconds, clock.calls
    per_replan = {
        name: 1e3 * sec.get(name, 0.0) / replans for name in ("sampling", "U-Net", "guidance", "scoring")
    }
    for name in StageClock.PER_STEP:  # at the steps that replanned; beside, the mean over every step
        per_replan[name] = 1e3 * clock.at_replans.get(name, 0.0) / replans
    per_step = {name: 1e3 * sec.get(name, 0.0) / max(calls.get(name, 0), 1) for name in StageClock.PER_STEP}
    rest = per_replan["sampling"] - per_replan["U-Net"] - per_replan["guidance"]
    total = statistics.fmean(times)
    stages = sum(per_replan[name] for name in ("sampling", "scoring", *StageClock.PER_STEP))
    unet_calls = calls.get("U-Net", 0) / replans
    print(
        f"(f) where a replan's time goes: K={k}, B=1, through select_action over whole episodes of {where} "
        f"({replans} replans in {steps} steps; {path}, DDIM {cfg.num_inference_steps}, warm start "
        f"{cfg.warm_start_step}, sampling_guidance {cfg.sampling_guidance:g}; means):"
    )
    print(
        f"    a replan step (select_action)      {total:6.2f} ms (median {statistics.median(times):.2f} ms)"
    )
    print(
        f"    sampling                           {per_replan['sampling']:6.2f} ms: {unet_calls:.2f} U-Net calls "
        f"of {per_replan['U-Net'] / max(unet_calls, 1e-9):.2f} ms = {per_replan['U-Net']:.2f} ms, clearance "
        f"guidance {per_replan['guidance']:.2f} ms, the rest (conditioning, DDIM steps) {rest:.2f} ms"
    )
    print(f"    best-of-K scoring                  {per_replan['scoring']:6.2f} ms")
    for name, label in zip(StageClock.PER_STEP, ("safety view", "recheck"), strict=True):
        print(f"    {label:<35}{per_replan[name]:6.2f} ms (every step: {per_step[name]:.2f} ms)")
    print(f"    the stages' sum                    {stages:6.2f} ms")
    return (
        f"replan stages B=1 K={k}: U-Net {per_replan['U-Net']:.1f} ms ({unet_calls:.2f} calls), guidance "
        f"{per_replan['guidance']:.1f} ms, sampling's rest {rest:.1f} ms, scoring {per_replan['scoring']:.1f} ms, "
        f"view {per_replan['view']:.1f} ms, recheck {per_replan['recheck']:.1f} ms: the stages sum to {stages:.1f} of "
        f"{total:.1f} ms a replan step (ratio {stages / total:.2f}; {torch.get_num_threads()} thread(s))"
    )


def replay_scorer(calls, ours, base, repeats: int = 3) -> tuple[float, float, bool]:
    """Median ms a call of ``ours`` and ``base`` on the recorded ``calls`` [(args, kwargs)], each call
    timed ``repeats`` times with each (the fastest kept), the two interleaved in alternating order so
    that both see the same host speed; and whether they returned the same values on every call."""
    if not calls:
        return float("nan"), float("nan"), True
    fns, ms, same = (ours, base), ([], []), True
    for i, (args, kwargs) in enumerate(calls):
        values = [None, None]
        for j in (0, 1) if i % 2 == 0 else (1, 0):
            best = float("inf")
            for _ in range(repeats):
                t0 = time.perf_counter()
                values[j] = fns[j](*args, **kwargs)
                best = min(best, time.perf_counter() - t0)
            ms[j].append(1e3 * best)
        same = same and np.array_equal(values[0], values[1])
    return statistics.median(ms[0]), statistics.median(ms[1]), same


def safety_part(path: str, k: int, scenes: int, level: str | None = None) -> str:
    """Print part (e); return its headline: the replan latency at B=1 through ``select_action`` over
    whole episodes of ``scenes`` unseen paper scenes (``episode_replans_ms``), standard (K = 1) and with
    the safety layer's best-of-K (sampling the K candidates, then the scorer: footprint, cost-to-go
    progress, escape manoeuvres). The scorer's cost-to-go stops once the cells it reads are exact
    (``navigation.cost_to_go_at``); the baseline computes the whole field to convergence
    (``cost_to_go(...).at``, as before), timed on the calls a best-of-K run made (``replay_scorer``:
    the same inputs, the two interleaved, so the host's drift between runs does not enter the ratio),
    the values checked equal. ``level``: that level's scenes and conditions instead of unseen paper
    scenes."""
    from lerobot_formation.core.safety import filters as safety
    from lerobot_formation.core.world import navigation
    from lerobot_formation.policy.configuration_formation_diffusion import TUNED_SAMPLING_GUIDANCE

    policy, pre, post, seeds, env_kwargs, where = layer_setup(path, scenes, level)
    cfg = policy.config

    def whole_field(obstacles, goal, points, rows=None, bilinear=False, **kw):
        return navigation.cost_to_go(obstacles, goal, **kw).at(points, rows, bilinear)

    shipped_scorer, calls = safety.cost_to_go_at, []

    def recording(*args, **kwargs):  # the shipped scorer; its inputs kept for the replay
        calls.append(copy.deepcopy((args, kwargs)))
        return shipped_scorer(*args, **kwargs)

    runs = {}
    plain = f"K={k}, plain trace"
    shipped = {"sampling_guidance": cfg.sampling_guidance, "safety_search": cfg.safety_search}
    # every variant sets these fields: reconfigure keeps what an earlier variant changed
    guided = {**shipped, "sampling_guidance": cfg.sampling_guidance or TUNED_SAMPLING_GUIDANCE}
    unguided = {**shipped, "sampling_guidance": 0.0}
    # best-of-K with the other guidance setting than the checkpoint's
    other_setting = "unguided" if cfg.sampling_guidance else "guided"
    other_guidance = f"K={k}, {other_setting}"
    variants = [  # label, K, scorer, config fields, plain trace
        ("K=1", 1, None, unguided, False),  # standard sampling
        ("K=1, guided", 1, None, guided, False),
        (f"K={k}", k, None, shipped, False),
        (other_guidance, k, None, unguided if cfg.sampling_guidance else guided, False),
        (f"K={k}, recorded", k, recording, shipped, False),  # its calls for the scorer's replay
    ]
    unsearched = f"K={k}, no lattice search"  # the previous default (safety_search 0)
    if cfg.safety_search:
        variants.append((unsearched, k, None, {**shipped, "safety_search": 0}, False))
    variants.append((plain, k, None, shipped, True))  # last: it traces again on its first call
    for label, kk, scorer, fields, plain_trace in variants:
        policy.reconfigure(num_candidates=kk, **fields)  # a new config: a fresh replanner (reset)
        runs[label] = episode_replans_ms(
            policy, pre, post, cfg.obstacle_encoding, seeds, scorer, env_kwargs, plain_trace
        )
    same = np.array_equal(np.asarray(runs[f"K={k}"][1]), np.asarray(runs[f"K={k}, recorded"][1]))
    ctg_ours, ctg_base, same_values = replay_scorer(calls, shipped_scorer, whole_field)
    del runs[f"K={k}, recorded"]  # the recording's copies are in its time: not a latency figure
    print(
        f"(e) safety layer: every replan at B=1 through select_action (pre/post processors) over whole "
        f"episodes of {where}; {path} (DDIM {cfg.num_inference_steps}, warm start "
        f"{cfg.warm_start_step}, {cfg.chunk_smoothing} smoothing passes, traced U-Net):"
    )
    med = {}
    for label, (times, _) in runs.items():
        med[label] = statistics.median(times)
        print(
            f"    {label:<28} {len(times):4d} replans: median {med[label]:6.2f} ms, mean "
            f"{statistics.fmean(times):6.2f} ms, 90th percentile {np.percentile(times, 90):6.2f} ms"
        )
    ours = med[f"K={k}"]
    print(f"    the recorded run took the same actions: {same}")
    print(
        f"    the scorer's cost-to-go on the {len(calls)} recorded calls: median {ctg_ours:.3f} ms a call, the "
        f"whole field {ctg_base:.3f} ms ({ctg_base / ctg_ours:.2f}x); the same values: {same_values}"
    )
    extra = f", {other_setting} {med[other_guidance]:.1f} ms, K=1 guided {med['K=1, guided']:.1f} ms"
    if unsearched in med:
        extra = f", without the lattice search {med[unsearched]:.1f} ms (ratio {ours / med[unsearched]:.2f}x){extra}"
    return (
        f"replan latency B=1 via select_action over whole episodes: K={k} with the safety layer {ours:.1f} ms"
        f"{extra} (its cost-to-go {ctg_ours:.2f} ms a call, the whole field {ctg_base:.2f} ms, ratio "
        f"{ctg_base / ctg_ours:.2f}x; plain trace "
        f"{med[plain]:.1f} ms, ratio {med[plain] / ours:.2f}x), K=1 {med['K=1']:.1f} ms "
        f"(medians; {torch.get_num_threads()} thread(s))"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--policy.path", dest="policy_path", default=None, help="default model (part b)")
    ap.add_argument("--paper-config", default=str(REPO / "configs" / "formation_diffusion_paper.json"))
    ap.add_argument("--ddim-steps", type=int, default=10, help="our fastest setting's DDIM steps (part a)")
    ap.add_argument("--batch", type=int, default=100, help="episodes per batched replan")
    ap.add_argument("--repeats", type=int, default=5)
    add_threads_argument(ap, "torch threads")
    ap.add_argument("--quick", action="store_true", help="smoke run: 1 repeat, batch 10")
    ap.add_argument("--parts", default="abc", help="which parts to run, e.g. 'c' (see the docstring)")
    ap.add_argument("--lean-candidates", type=int, nargs="+", default=[1, 10], help="K in part (c)")
    ap.add_argument("--lean-steps", type=int, nargs="+", default=[10, 3], help="DDIM steps in part (c)")
    ap.add_argument("--lean-repeats", type=int, default=30, help="timing rounds in part (c)")
    ap.add_argument("--safety-scenes", type=int, default=10, help="unseen scenes of part (e)")
    ap.add_argument(
        "--level", default=None, help="part (e) on this level's scenes and conditions (e.g. level5)"
    )
    args = ap.parse_args(argv)
    if args.quick:
        args.repeats, args.batch, args.lean_repeats = 1, min(args.batch, 10), min(args.lean_repeats, 5)
    apply_threads(args.threads)
    threads = torch.get_num_threads()

    from lerobot_formation.bench.diffusion_controller import DiffusionController
    from lerobot_formation.policy.checkpoint import load_policy
    from lerobot_formation.policy.configuration_formation_diffusion import LAYER_OFF

    print(
        f"torch threads {threads}, {os.cpu_count()} CPUs; median of {args.repeats} after a warm-up",
        flush=True,
    )

    # (b) The default model.
    if args.policy_path and "b" in args.parts:
        bundle = load_policy(args.policy_path)
        bundle[0].reconfigure(**LAYER_OFF)  # the network's replan: standard sampling, K = 1
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

    path = args.policy_path or str(REPO / "pretrained" / "formation_diffusion_route_v1")  # parts c-f
    if "a" in args.parts:
        paper_part(args)
    if "c" in args.parts:
        print(lean_part(path, args.lean_candidates, args.lean_steps, args.lean_repeats))
    if "e" in args.parts:
        print(safety_part(path, max(args.lean_candidates), args.safety_scenes, args.level))
    if "f" in args.parts:
        print(stage_part(path, max(args.lean_candidates), args.safety_scenes, args.level))
    return 0


def paper_part(args) -> None:
    """Part (a): the paper-size network."""
    from lerobot_formation.bench.diffusion_controller import DiffusionController

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


if __name__ == "__main__":
    raise SystemExit(main())
