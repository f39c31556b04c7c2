"""The diffusion policy behind the batched evaluation engine (issue 5 tests).

A tiny checkpoint is trained once for this module through the real ``lerobot-train`` console script
(tiny config, 4 steps) on a tiny PAC dataset, as ``tests/plugin/test_plugin_e2e.py`` does. Then:

(a) the engine (``evaluate(DiffusionController(path), scenes)``) against LeRobot's own evaluation:
    1. step for step: with the same initial noise (the stock loop is given each episode's draws
       from the engine's per-episode streams), the engine's actions equal those of
       ``lerobot.scripts.lerobot_eval.rollout`` (the loop ``lerobot-eval`` runs) on a vector env of
       the same scenes, over three replans, within 1e-5: the engine runs each episode's denoiser
       call alone (its rounding independent of the batch, ``Replanner.act``) and the stock loop one
       call for the batch, whose float rounding differs by ~1e-6 (1.7e-6 seen); an error of the
       observations, their history, the normalisation, the chunk alignment or the action execution
       moves actions by 1e-2 or more. It holds while every episode is alive: after one ends, the
       stock loop still replans it and the engine does not;
    2. whole episodes through the ``lerobot-eval`` console script: the same success rate and mean
       episode reward on the same scenes, within sampling noise (tolerance below);
(b) the DDIM step override (``set_inference_steps``) sets the sampler and its step count on both the
    live and the EMA model, is what the engine and ``select_action`` run, and rejects bad counts.

Tolerance of (a2): the two paths draw their noise from different generators once episodes end, so
their episodes are different samples of the same process and cannot be compared one by one.
lerobot-eval runs 100 episodes (scene i = seed i); the engine runs the same 100 scenes with 5 noise
seeds (marked slow; the default run has a copy on 20 scenes with 2 noise seeds, whose bounds are
wider). Each statistic must agree within 3 standard errors of the difference (binomial for the
success rate, Welch for the reward): about a 0.3 % false alarm if the two paths are the same
process; both runs are deterministic, and the standard errors ignore that both sides share the
scenes, which only widens the bound. The scenes are an empty field with a goal 0.56-1.04 m ahead and
30-step episodes, where this barely trained policy succeeds about half the time, so the statistics
move with the executed actions' scale (without the unnormalisation the engine's success drops from
~0.47 to ~0.29, beyond the ~0.16 bound) and with the episode rules (length, success, reward). A
4-step policy barely reacts to its observations, which is why (a1) checks those exactly.
"""

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from lerobot_formation.bench.diffusion_controller import (
    DiffusionController,
    EpisodeNoise,
    episode_noise_seeds,
)
from lerobot_formation.bench.evaluation import evaluate
from lerobot_formation.core.episodes.rollout import COLLISION, SUCCESS
from lerobot_formation.core.perception.conditions import Perception
from lerobot_formation.core.world.dynamics import FormationParams, initial_state
from lerobot_formation.core.world.sampling import UNSEEN_SEED_START, sample_scenes
from lerobot_formation.core.world.scene_files import load_scenes, save_scenes, scenes_from_list
from lerobot_formation.policy.checkpoint import load_policy, set_inference_steps

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
TINY = REPO / "configs" / "formation_diffusion_tiny.json"
REPO_ID = "local/formation_engine_test"
EPISODES = 100  # lerobot-eval episodes (one batch of 100 sync envs)
ENGINE_SEEDS = 5  # noise seeds of the engine over the same scenes
EPISODE_LENGTH = 30
SMOKE_EPISODES, SMOKE_ENGINE_SEEDS = 20, 2  # the fast tier's copy of (a2); the full one is marked slow


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("engine")


@pytest.fixture(scope="module")
def checkpoint(workdir, run_cli) -> Path:
    """A tiny formation_diffusion checkpoint trained through the lerobot-train CLI."""
    sys.path.insert(0, str(REPO))
    try:
        from datasets_scripts.generate_pac_dataset import main as generate
    finally:
        sys.path.remove(str(REPO))
    root = workdir / "dataset"
    generate(["--episodes", "3", "--seed", "0", "--repo-id", REPO_ID, "--root", str(root), "--no-progress"])
    out = workdir / "train"
    run_cli(
        "lerobot-train",
        f"--config_path={TINY}",
        f"--dataset.repo_id={REPO_ID}",
        f"--dataset.root={root}",
        f"--output_dir={out}",
        "--env_eval_freq=0",
        cwd=workdir,
    )
    return out / "checkpoints" / "last" / "pretrained_model"


@pytest.fixture(scope="module")
def bundle(checkpoint):
    """(policy, preprocessor, postprocessor), shared by the tests that do not change the sampler."""
    return load_policy(checkpoint)


def near_goal_scenes(n: int, seed: int = 0):
    """Empty field; the goal 0.56-1.04 m from the start, within 34 deg of the initial heading (+y)."""
    rng = np.random.default_rng(seed)
    heading = np.pi / 2 + rng.uniform(-0.6, 0.6, n)
    dist = 0.8 * rng.uniform(0.7, 1.3, n)
    goals = np.stack([dist * np.cos(heading), dist * np.sin(heading)], axis=1)
    return scenes_from_list([{"obstacles": [], "goal": g.tolist()} for g in goals])


def engine_sum_reward(rec, scenes) -> np.ndarray:
    """FormationEnv's episode return: progress to the goal, +1 on success, -1 on collision."""
    end = rec.poses[np.arange(len(rec)), rec.steps, :2]
    progress = np.linalg.norm(scenes.start[:, :2] - scenes.goal, axis=1) - np.linalg.norm(
        end - scenes.goal, axis=1
    )
    return progress + (rec.outcome == SUCCESS) - (rec.outcome == COLLISION)


def test_engine_actions_equal_lerobot_rollout(checkpoint, bundle, workdir):
    from lerobot.envs.factory import make_env_pre_post_processors
    from lerobot.scripts.lerobot_eval import rollout
    from lerobot.utils.constants import ACTION

    from lerobot_formation.core.world.dynamics import clip_action
    from lerobot_formation.envs.env_config import FormationEnvConfig

    B, T, seed = 8, 24, 7  # three replans of n_action_steps = 8; far goals, so all stay alive
    scenes_file = workdir / "parity_scenes.json"
    save_scenes(sample_scenes(UNSEEN_SEED_START + np.arange(B)), scenes_file)
    scenes = load_scenes(scenes_file)
    policy, pre, post = bundle
    params = FormationParams(max_steps=T)
    ctrl = DiffusionController(checkpoint, seed=seed, policy_bundle=bundle)
    rec = evaluate(ctrl, scenes, params)
    assert (rec.steps == T).all(), "an episode ended early: the two loops would replan other episodes"

    env_cfg = FormationEnvConfig(scenes_file=str(scenes_file), episode_length=T)
    env = env_cfg.create_envs(B, use_async_envs=False)["formation"][0]
    env_pre, env_post = make_env_pre_post_processors(env_cfg, policy.config)
    # the stock loop calls select_action(batch) and would draw from the global generator: at each of
    # its replans (LeRobot's action queue empty) it gets every episode's next draw of its own stream
    noise = EpisodeNoise(
        episode_noise_seeds(seed, ctrl.name, scenes.seeds, scenes.goal), (policy.config.horizon, 2)
    )
    select = policy.select_action

    def select_with_episode_noise(batch):
        replan = len(policy._queues[ACTION]) == 0
        return select(batch, noise=noise(torch.arange(B), 1) if replan else None)

    policy.select_action = select_with_episode_noise
    try:
        stock = rollout(env, policy, env_pre, env_post, pre, post, seeds=list(range(B)))
    finally:
        del policy.select_action  # the shared policy's own method again
        env.close()
    stock_actions = clip_action(stock["action"].numpy().astype(np.float64), params)  # the env clips
    np.testing.assert_allclose(rec.actions, stock_actions, rtol=0, atol=1e-5)  # module docstring (a1)


@pytest.mark.slow
def test_engine_success_matches_lerobot_eval(checkpoint, bundle, workdir, run_cli):
    check_success_matches_lerobot_eval(checkpoint, bundle, workdir, run_cli, EPISODES, ENGINE_SEEDS)


def test_engine_success_matches_lerobot_eval_smoke(checkpoint, bundle, workdir, run_cli):
    """The fast tier's copy of the test above, scaled down (same checks, wider 3-SE bounds)."""
    check_success_matches_lerobot_eval(
        checkpoint, bundle, workdir, run_cli, SMOKE_EPISODES, SMOKE_ENGINE_SEEDS
    )


def check_success_matches_lerobot_eval(
    checkpoint, bundle, workdir, run_cli, episodes: int, engine_seeds: int
):
    """(a2) on ``episodes`` near-goal scenes: lerobot-eval once, the engine with ``engine_seeds`` seeds."""
    scenes = near_goal_scenes(episodes)
    scenes_file = workdir / f"near_goal_scenes_{episodes}.json"
    save_scenes(scenes, scenes_file)
    out = workdir / f"eval_{episodes}"
    run_cli(
        "lerobot-eval",
        f"--policy.path={checkpoint}",
        "--policy.device=cpu",
        "--env.type=formation",
        f"--env.scenes_file={scenes_file}",
        f"--env.episode_length={EPISODE_LENGTH}",
        "--seed=0",  # eval seed i -> scene i of the file
        f"--eval.n_episodes={episodes}",
        f"--eval.batch_size={episodes}",
        "--eval.use_async_envs=false",
        f"--output_dir={out}",
        cwd=workdir,
    )
    metrics = json.loads((out / "eval_info.json").read_text())["per_task"][0]["metrics"]
    stock_success = np.asarray(metrics["successes"], dtype=float)
    stock_reward = np.asarray(metrics["sum_rewards"], dtype=float)
    assert len(stock_success) == episodes

    params = FormationParams(max_steps=EPISODE_LENGTH)
    succ, reward = [], []
    for seed in range(engine_seeds):
        rec = evaluate(DiffusionController(checkpoint, seed=seed, policy_bundle=bundle), scenes, params)
        succ.append(rec.outcome == SUCCESS)
        reward.append(engine_sum_reward(rec, scenes))
    engine_success = np.concatenate(succ).astype(float)
    engine_reward = np.concatenate(reward)

    p_s, p_e = stock_success.mean(), engine_success.mean()
    # Meaningful only if the outcome is uncertain: neither (nearly) always nor never a success.
    assert 0.15 <= p_e <= 0.85, f"engine success {p_e:.2f}: the scenes no longer discriminate"
    p = np.concatenate([stock_success, engine_success]).mean()
    se = np.sqrt(p * (1 - p) * (1 / len(stock_success) + 1 / len(engine_success)))
    assert abs(p_s - p_e) <= 3 * se, (
        f"success: lerobot-eval {p_s:.2f} vs engine {p_e:.2f} (3 SE = {3 * se:.2f})"
    )
    se_r = np.sqrt(
        stock_reward.var(ddof=1) / len(stock_reward) + engine_reward.var(ddof=1) / len(engine_reward)
    )
    assert abs(stock_reward.mean() - engine_reward.mean()) <= 3 * se_r, (
        f"mean episode reward: lerobot-eval {stock_reward.mean():.3f} vs engine "
        f"{engine_reward.mean():.3f} (3 SE = {3 * se_r:.3f})"
    )


def count_denoiser_calls(model, fn) -> int:
    calls = []
    handle = model.unet.register_forward_hook(lambda *_: calls.append(1))
    try:
        fn()
    finally:
        handle.remove()
    return len(calls)


def test_ddim_step_override(checkpoint):
    from diffusers.schedulers.scheduling_ddim import DDIMScheduler

    policy, pre, post = load_policy(checkpoint)  # own copy: the sampler is changed below
    cfg = policy.config
    ctrl = DiffusionController(checkpoint, policy_bundle=(policy, pre, post))
    scenes = sample_scenes(UNSEEN_SEED_START + np.arange(3))
    idx = np.arange(3)

    def plan():  # one replan of all three episodes: a fresh start
        state = initial_state(scenes.start, ctrl.params)
        ctrl.reset(Perception.exact(scenes, state))
        return ctrl.act(Perception.exact(scenes, state), idx)

    # the engine runs each episode's sampler call alone: three episodes, three calls per step
    assert count_denoiser_calls(policy.ema_diffusion, plan) == 3 * cfg.num_inference_steps  # checkpoint's: 4

    set_inference_steps(policy, None)  # keeps the checkpoint's sampler
    assert count_denoiser_calls(policy.ema_diffusion, plan) == 3 * cfg.num_inference_steps

    set_inference_steps(policy, 2)
    for model in (policy.diffusion, policy.ema_diffusion):
        assert isinstance(model.noise_scheduler, DDIMScheduler)
        assert model.num_inference_steps == 2
        assert model.noise_scheduler.config.num_train_timesteps == cfg.num_train_timesteps
    assert count_denoiser_calls(policy.ema_diffusion, plan) == 3 * 2
    assert plan().shape == (3, 2)

    # The stock select_action runs the overridden sampler too.
    obs = pre({"observation.state": torch.zeros(1, 7), "observation.environment_state": torch.zeros(1, 51)})

    def select():
        policy.reset()
        policy.select_action(obs)

    assert count_denoiser_calls(policy.ema_diffusion, select) == 2

    for bad in (0, -1, cfg.num_train_timesteps + 1):
        with pytest.raises(ValueError, match="inference steps must be in"):
            set_inference_steps(policy, bad)
        with pytest.raises(ValueError, match="inference steps must be in"):
            DiffusionController(checkpoint, num_inference_steps=bad, policy_bundle=(policy, pre, post))
