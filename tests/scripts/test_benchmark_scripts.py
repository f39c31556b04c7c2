"""The benchmark scripts (their --help and the flags it lists: tests/scripts/test_scripts_smoke.py's
test_help): bench_sampling_steps' pure helpers, bench_eval_speed's stock command,
and bench_route_encoding at two scenes of three steps (its output lines and its input check)."""

import importlib.util
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _script(relpath: str):
    path = REPO / relpath
    spec = importlib.util.spec_from_file_location(f"_bench_test_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_eval_speed_stock_command_carries_the_safety_layer(tmp_path):
    import argparse

    m = _script("benchmarks/bench_eval_speed.py")
    args = argparse.Namespace(
        policy_path="ckpt", episode_length=60, episodes=10, candidates=1, safety_filter="none"
    )
    plain = m.stock_command(args, 10, False, tmp_path / "s.json", "nearest", tmp_path / "o")
    # K and the filter always given: the checkpoint's own (the shipped one's layer) are not the run's
    assert "--policy.num_candidates=1" in plain and "--policy.safety_filter=none" in plain
    assert "--eval.batch_size=10" in plain and "--eval.use_async_envs=false" in plain
    args.candidates, args.safety_filter = 10, "cbf"
    safe = m.stock_command(args, None, None, tmp_path / "s.json", "nearest", tmp_path / "o")
    assert "--policy.num_candidates=10" in safe and "--policy.safety_filter=cbf" in safe
    assert not any(c.startswith("--eval.batch_size") for c in safe)


def test_eval_speed_stock_command_plays_a_level_with_its_conditions(tmp_path):
    """--level: lerobot-eval plays the level from its own first seed, and its safety layer is told the
    level's actuator and moving obstacles through real fields of the policy config."""
    import argparse
    import dataclasses

    from lerobot_formation.bench.controllers import safety_settings
    from lerobot_formation.core.episodes.levels import get_level
    from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig

    m = _script("benchmarks/bench_eval_speed.py")
    level = get_level("level5")
    args = argparse.Namespace(
        policy_path="ckpt",
        episode_length=600,
        episodes=200,
        candidates=10,
        safety_filter="cbf",
    )
    cmd = m.stock_command(
        args,
        50,
        False,
        tmp_path / "s.json",
        "nearest+route",
        tmp_path / "o",
        safety_settings(level.conditions),
        level,
    )
    assert "--env.level=level5" in cmd and f"--seed={level.seed}" in cmd
    assert not any(c.startswith("--env.scenes_file") for c in cmd)
    assert (
        "--policy.safety_world.action_delay=1" in cmd and "--policy.safety_world.moving_obstacles=true" in cmd
    )
    assert "--policy.safety_world.max_linear_accel=0.5" in cmd
    names = {f.name for f in dataclasses.fields(FormationDiffusionConfig)}
    policy_fields = [
        c[len("--policy.") :].split("=")[0].split(".")[0] for c in cmd if c.startswith("--policy.")
    ]
    assert set(policy_fields) - {"path", "device"} <= names


def test_sampling_steps_helpers():
    m = _script("benchmarks/bench_sampling_steps.py")
    assert m.int_list("10, 1,2,2") == [10, 1, 2]
    with pytest.raises(Exception, match="steps must be >= 1"):
        m.int_list("0")
    assert m.same_rate(60, 100, 66, 100) and not m.same_rate(50, 100, 66, 100)  # z = 0.88 vs 2.3
    assert m.same_rate(0, 10, 0, 10) and not m.same_rate(0, 100, 100, 100)
    res = {
        "k1": {"a": {"success_rate": 0.1, "n_episodes": 100}, "b": {"success_rate": 0.6, "n_episodes": 100}},
        "k3": {"a": {"success_rate": 0.5, "n_episodes": 100}, "b": {"success_rate": 0.55, "n_episodes": 100}},
        "ref": {
            "a": {"success_rate": 0.55, "n_episodes": 100},
            "b": {"success_rate": 0.6, "n_episodes": 100},
        },
    }
    assert m.within_noise(res, "ref") == ["k3", "ref"]  # k1 matches on "b" only: not within noise
    sets = {"a": {"wall_s": 2.0, "replans": 10}, "b": {"wall_s": 1.0, "replans": 20}}
    assert m.seconds_per_replan(sets) == pytest.approx(0.1)
    assert m.seconds_per_replan({"a": {"wall_s": 1.0, "replans": None}}) is None


def test_route_encoding_bench_times_both_encodings_and_ends_with_the_ratio(capsys):
    m = _script("benchmarks/bench_route_encoding.py")
    m.main(["--scenes", "2", "--steps", "3"])
    lines = capsys.readouterr().out.strip().splitlines()
    assert any(line.strip().startswith("nearest ") and "(6 steps)" in line for line in lines), lines
    assert any(line.strip().startswith("nearest+route") and "(6 steps)" in line for line in lines), lines
    assert lines[-1].startswith("step with the route hint:") and lines[-1].endswith("x the nearest step")
    with pytest.raises(ValueError, match="--scenes and --steps must be >= 1, got 0, 3"):
        m.main(["--scenes", "0", "--steps", "3"])


@pytest.mark.slow
def test_replan_latency_under_a_level_runs_its_scenes_with_the_safety_layer_told_the_conditions(capsys):
    """Part (e) with --level: the level's scenes under its conditions, and the policy's safety layer
    configured for them (the delay and rate limits of level5, moving obstacles predicted)."""
    import torch

    bench = _script("benchmarks/bench_replan_latency.py")
    seen, plain = [], []
    real = bench.episode_replans_ms

    def spy(policy, *args, **kwargs):
        world = policy.config.safety_world
        seen.append((world.action_delay, world.moving_obstacles, args[5]))
        plain.append(args[6])
        guided.append((policy.config.num_candidates, policy.config.sampling_guidance))
        return real(policy, *args, **kwargs)

    guided = []
    bench.episode_replans_ms = spy
    torch.set_num_threads(1)
    headline = bench.safety_part(str(REPO / "pretrained" / "formation_diffusion_route_v1"), 2, 1, "level5")
    assert "K=2 with the safety layer" in headline and "plain trace" in headline
    assert "its cost-to-go" in headline and "the whole field" in headline
    assert "1 scenes of level5 under its conditions" in capsys.readouterr().out
    assert plain.count(True) == 1  # the policy's trace against a plain one, in the same run
    assert all(delay == 1 and moving for delay, moving, _ in seen), seen
    # standard sampling (unguided) and one guided sample at K = 1; best-of-K with the checkpoint's
    # guidance (the K = 2 run as shipped) and with the other setting; every other variant as the checkpoint
    g = guided[2][1]
    assert (
        guided[:4] == [(1, 0.0), (1, g or 1.0), (2, g), (2, 0.0 if g else 1.0)] and "K=1 guided" in headline
    )
    assert all(gg == g for _, gg in guided[4:])
    assert all(env_kwargs["conditions"].moving_obstacles == 2 for *_, env_kwargs in seen)


def test_scorer_replay_times_both_scorers_on_the_same_calls_and_compares_their_values():
    """``replay_scorer``: every recorded call runs with both scorers (in alternating order), the
    medians are per call, and a scorer that returns other values on some call is reported."""
    import numpy as np

    bench = _script("benchmarks/bench_replan_latency.py")
    calls = [((np.arange(3.0),), {"scale": 2.0}), ((np.ones(2),), {"scale": 1.0})]
    seen = []

    def ours(x, scale):
        seen.append("ours")
        return x * scale

    def same(x, scale):
        seen.append("base")
        return scale * x

    def other(x, scale):
        return x * scale + (x[0] > 0)

    t_ours, t_base, equal = bench.replay_scorer(calls, ours, same, repeats=2)
    assert equal and t_ours > 0 and t_base > 0
    assert seen == ["ours"] * 2 + ["base"] * 2 + ["base"] * 2 + ["ours"] * 2  # interleaved, alternating
    assert not bench.replay_scorer(calls, ours, other, repeats=1)[2]  # the second call differs
    assert bench.replay_scorer([], ours, same)[2]


@pytest.mark.slow
def test_replan_stages_time_every_stage_and_restore_the_replanner(capsys):
    """Part (f): each stage of a best-of-K replan is timed (the denoiser calls and the guidance inside
    the sampling), the stages' sum is set beside the measured replan step, and every patched
    function is the original again after the run."""
    import torch

    from lerobot_formation.policy import modeling_formation_diffusion as modeling
    from lerobot_formation.policy.replanner import Replanner

    bench = _script("benchmarks/bench_replan_latency.py")
    before = (
        Replanner.view,
        Replanner._recheck,
        Replanner.choose,
        Replanner._guide,
        modeling._LeanCache.unet,
    )
    torch.set_num_threads(1)
    headline = bench.stage_part(str(REPO / "pretrained" / "formation_diffusion_route_v1"), 2, 1, "level5")
    after = (Replanner.view, Replanner._recheck, Replanner.choose, Replanner._guide, modeling._LeanCache.unet)
    assert after == before
    out = capsys.readouterr().out
    assert "1 scenes of level5 under its conditions" in out and "sampling_guidance 1" in out
    assert out.count("(every step: ") == 2  # the view and the recheck: at the replan steps, and over all
    calls = float(headline.split("U-Net ")[1].split("(")[1].split(" calls")[0])
    assert 1.0 <= calls <= 4.0  # DDIM 4, warm-started replans run 3 (the first 4)
    ratio = float(headline.split("(ratio ")[1].split(";")[0])
    assert 0.5 < ratio <= 1.05  # the stages are inside the replan step, and most of it


def test_unet_flops_counts_two_per_multiply_add():
    import torch

    m = _script("benchmarks/bench_unet_backends.py")
    net = torch.nn.Sequential(
        torch.nn.Conv1d(3, 4, 5, padding=2), torch.nn.Flatten(), torch.nn.Linear(4 * 16, 2)
    )
    x = torch.zeros(2, 3, 16)
    conv = 2 * (2 * 4 * 16) * 3 * 5  # outputs x inputs per output
    linear = 2 * (2 * 2) * 64
    assert m.unet_flops(net, (x,)) == conv + linear


def test_median_seconds_warms_up_then_takes_the_median_of_the_timed_calls(monkeypatch):
    """The benchmarks' one timing rule: warm-up calls are not timed, one slow call does not move it."""
    from lerobot_formation.bench import timing

    clock = iter([0.0, 1.0, 10.0, 10.5, 20.0, 29.0])  # timed calls of 1.0, 0.5 and 9.0 s
    monkeypatch.setattr(timing.time, "perf_counter", lambda: next(clock))
    calls = []
    assert timing.median_seconds(lambda: calls.append(1), repeats=3, warmup=2) == 1.0
    assert len(calls) == 5
    with pytest.raises(ValueError, match="repeats must be >= 1, got 0"):
        timing.median_seconds(lambda: None, repeats=0)
    with pytest.raises(ValueError, match="warmup must be >= 0, got -1"):
        timing.median_seconds(lambda: None, repeats=1, warmup=-1)
