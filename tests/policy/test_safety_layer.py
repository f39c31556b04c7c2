"""The safety layer inside ``formation_diffusion`` (config fields num_candidates / safety_filter)."""

import dataclasses

import numpy as np
import pytest
import torch
from lerobot.utils.constants import OBS_ENV_STATE, OBS_STATE
from plugin_helpers import (
    HORIZON,
    N_OBS,
    formation_features,
    nearest_config,
    save_nearest_checkpoint,
    tiny_config,
)

from lerobot_formation.core.encodings.obstacle_grid import environment_state
from lerobot_formation.core.perception.conditions import Perception
from lerobot_formation.core.safety import layer as safety_layer
from lerobot_formation.core.safety.layer import KnownWorld
from lerobot_formation.core.safety.replan_blend import smooth_chunks
from lerobot_formation.core.world.scenes import FAR
from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy


def _env_state(obstacles, pose=(0.0, 0.0, np.pi / 2), goal=(0.0, 8.0)):
    obs = np.array([obstacles if obstacles else [[FAR, FAR, 0.0]]], dtype=np.float64)
    mask = obs[..., 2] > 0
    return torch.from_numpy(
        environment_state(obs, mask, np.array([goal]), "nearest", pose=np.array([pose]))
    ).float()


def _batch(env):
    return {OBS_STATE: torch.zeros(len(env), 7), OBS_ENV_STATE: env}


def test_safety_layer_needs_egocentric_encoding_and_fixed_bounds():
    with pytest.raises(ValueError, match="needs an egocentric obstacle encoding"):
        tiny_config(num_candidates=4)  # grid encoding (51 values)
    with pytest.raises(ValueError, match="needs an egocentric obstacle encoding"):
        nearest_config(safety_filter="cbf", fixed_action_bounds=False)
    with pytest.raises(ValueError, match="needs an egocentric obstacle encoding"):  # an override, too
        dataclasses.replace(tiny_config(), num_candidates=4)
    with pytest.raises(ValueError, match="safety_filter must be one of"):
        nearest_config(safety_filter="qp")
    with pytest.raises(ValueError, match="obstacle_encoding='nearest'"):
        inputs, outputs = formation_features(env_dim=51)
        tiny_config(
            input_features=inputs, output_features=outputs, obstacle_encoding="nearest"
        ).validate_features()
    cfg = tiny_config()
    cfg.validate_features()
    assert cfg.obstacle_encoding == "grid"  # the default, stored; never guessed from the size
    inputs, outputs = formation_features(env_dim=66)  # a "grid+list" observation
    with pytest.raises(ValueError, match=r"obstacle_encoding='grid'.*--env.obstacle_encoding=grid"):
        tiny_config(input_features=inputs, output_features=outputs).validate_features()


def test_one_candidate_without_filter_equals_standard_sampling():
    torch.manual_seed(0)
    policy = FormationDiffusionPolicy(nearest_config()).eval()
    env = _env_state([[0.5, 2.0, 0.4]])
    stacked = {k: v[:, None].repeat(1, N_OBS, 1) for k, v in _batch(env).items()}
    noise = torch.randn(1, HORIZON, 2, generator=torch.Generator().manual_seed(3))
    chunks = policy.sample_action_chunks(stacked, 1, noise=noise)
    stock = policy.ema_diffusion.generate_actions(stacked, noise=noise)
    torch.testing.assert_close(chunks[:, 0, : stock.shape[1]], stock, rtol=0, atol=0)
    # the same through select_action: the CBF filter with nothing nearby leaves every action as is
    a = FormationDiffusionPolicy(nearest_config()).eval()
    b = FormationDiffusionPolicy(nearest_config(safety_filter="cbf")).eval()
    b.load_state_dict(a.state_dict())
    empty = _env_state([])
    for _ in range(3):
        torch.testing.assert_close(
            b.select_action(_batch(empty), noise=noise.clone()),
            a.select_action(_batch(empty), noise=noise.clone()),
        )
    assert b.safety_stats["filter_interventions"] == 0 and b.safety_stats["steps"] == 3


def test_select_action_with_candidates_and_filter_counts_its_interventions(monkeypatch):
    monkeypatch.setattr(safety_layer, "CBF_RATE", 2.0)  # the barrier numbers below are alpha = 2's
    torch.manual_seed(0)
    # K = 1: best-of-K would pick a safe escape manoeuvre here, which the filter then leaves as is
    policy = FormationDiffusionPolicy(nearest_config(num_candidates=1, safety_filter="cbf")).eval()
    env = _env_state([[0.5, 0.55, 0.2], [-0.5, 0.6, 0.2]])  # right in front of both leaders
    for _ in range(10):
        a = policy.select_action(_batch(env))
        assert a.shape == (1, 2)
        v, w = policy.unnormalize_action(a)[0].tolist()
        # the barriers of L2 (h = 0.15) and L1 (h = 0.2) at rate 2: -dh/dt = v +- 0.5 omega <= 2 h
        assert v + 0.5 * w <= 0.3 + 1e-5 and v - 0.5 * w <= 0.4 + 1e-5
    st = policy.safety_stats
    assert st["steps"] == 10 and st["filter_interventions"] >= 1
    assert st["replans"] > 2  # each intervention asks for a fresh plan at the next step
    picky = FormationDiffusionPolicy(nearest_config(num_candidates=4, safety_filter="cbf")).eval()
    for _ in range(10):
        v, w = picky.unnormalize_action(picky.select_action(_batch(env)))[0].tolist()
        assert v + 0.5 * w <= 0.3 + 1e-5 and v - 0.5 * w <= 0.4 + 1e-5
    assert picky.safety_stats["replans_none_safe"] >= 1 and picky.safety_stats["escapes"] >= 1


def test_action_normalisation_round_trips_the_fixed_bounds():
    policy = FormationDiffusionPolicy(nearest_config())
    raw = torch.tensor([[0.0, -1.5], [0.6, 1.5], [0.3, 0.0]])
    norm = policy.normalize_action(raw)
    torch.testing.assert_close(norm, torch.tensor([[-1.0, -1.0], [1.0, 1.0], [0.0, 0.0]]))
    torch.testing.assert_close(policy.unnormalize_action(norm), raw)


@pytest.mark.parametrize(
    ("k", "safety_filter", "warm"),
    [
        (3, "cbf", 0),
        (1, "none", 1),  # warm-started replans
        (3, "cbf", 2),  # ... after the filter cut a chunk short
    ],
)
def test_engine_and_select_action_feed_the_replanner_the_same(tmp_path, k, safety_filter, warm):
    """One episode, same noise: the engine's controller (its own observation histories, the
    checkpoint's preprocessor, the episode's noise stream) and the policy's select_action (LeRobot's
    queues, the path of lerobot-eval) run the same Replanner and give the same actions, replans and
    filter interventions."""
    from lerobot_formation.bench.diffusion_controller import (
        DiffusionController,
        EpisodeNoise,
        episode_noise_seeds,
    )
    from lerobot_formation.core.perception.observation import midpoint_state
    from lerobot_formation.core.world.dynamics import FormationParams, initial_state, step
    from lerobot_formation.core.world.scene_files import scenes_from_list
    from lerobot_formation.policy.checkpoint import load_policy

    path = save_nearest_checkpoint(
        tmp_path, num_candidates=k, safety_filter=safety_filter, warm_start_step=warm
    )
    scene = scenes_from_list([{"obstacles": [[0.6, 1.3, 0.35], [-1.0, 3.0, 0.5]], "goal": [0.5, 6.0]}])
    params = FormationParams()
    seed = 1  # a draw in which the filter intervenes in both "cbf" cases (11 of 12 seeds do)
    engine = DiffusionController(path, seed=seed, params=params)
    state = initial_state(scene.start, params)
    engine.reset(Perception.exact(scene, state))
    policy, pre, post = load_policy(path)
    policy.reset()
    # the engine's noise: the episode's own stream (run seed, controller name, scene)
    episode_noise = EpisodeNoise(
        episode_noise_seeds(seed, engine.name, scene.seeds, scene.goal), (HORIZON, 2)
    )
    for _ in range(30):
        a_engine = engine.act(Perception.exact(scene, state), np.array([0]))
        obs = {
            OBS_STATE: torch.from_numpy(midpoint_state(state.pose, state.velocity)),
            OBS_ENV_STATE: torch.from_numpy(
                environment_state(scene.obstacles, scene.mask, scene.goal, "nearest", pose=state.pose)
            ),
        }
        replan = bool(policy.replanner.needs_replan(torch.tensor([0]))[0])
        noise = episode_noise(torch.tensor([0]), k) if replan else None
        a_policy = post(policy.select_action(pre(obs), noise=noise)).numpy()
        np.testing.assert_allclose(a_policy, a_engine, atol=1e-5)
        state = step(state, a_engine, params)
    for key in ("replans", "steps", "filter_interventions", "replans_none_safe", "escapes", "stops"):
        assert engine.stats[key] == policy.safety_stats[key], key
    assert engine.stats["replans"] >= 4
    assert engine.stats["filter_interventions"] >= 1 or safety_filter == "none"


def test_a_bench_override_leaves_the_shared_policy_config_alone(tmp_path):
    """A controller's K and filter are a validated copy of the config (dataclasses.replace): the
    loaded policy, which other controllers share, keeps its own."""
    from lerobot_formation.bench.diffusion_controller import DiffusionController
    from lerobot_formation.policy.checkpoint import load_policy

    bundle = load_policy(save_nearest_checkpoint(tmp_path))
    safe = DiffusionController(
        None, policy_bundle=bundle, overrides={"num_candidates": 5, "safety_filter": "cbf"}
    )
    assert (safe.replanner.config.num_candidates, safe.replanner.config.safety_filter) == (5, "cbf")
    assert (bundle[0].config.num_candidates, bundle[0].config.safety_filter) == (1, "none")
    with pytest.raises(ValueError, match=r"num_candidates must be >= 1, got 0"):
        DiffusionController(None, policy_bundle=bundle, overrides={"num_candidates": 0})


def test_replan_experiment_settings_are_checked_with_their_value():
    from lerobot_formation.policy.replanner import ReplanExperiment, Replanner

    for bad in (-0.1, float("nan")):
        with pytest.raises(ValueError, match=rf"escape_advantage must be None or >= 0 \[m\], got {bad}"):
            ReplanExperiment(escape_advantage=bad)
    with pytest.raises(
        ValueError, match=r"blocked_fallback must be one of \('widest', 'stop'\), got 'brake'"
    ):
        ReplanExperiment(blocked_fallback="brake")
    with pytest.raises(ValueError, match=r"blend_steps must be >= 0, got -1"):
        ReplanExperiment(blend_steps=-1)
    policy = FormationDiffusionPolicy(nearest_config())
    with pytest.raises(ValueError, match=r"blend_steps must be in \[0, 15\] \(the chunk's length\), got 16"):
        Replanner.from_config(policy.config, experiment=ReplanExperiment(blend_steps=16))


def test_replan_blending_starts_a_new_chunk_at_the_executed_action():
    """With blending (an experiment setting) the first action after a replan moves from the last
    executed action toward the new chunk by 1 - 1/(m+1) of the way (``core.safety.replan_blend``)."""
    from lerobot_formation.policy.replanner import ReplanExperiment, Replanner, policy_sampler

    torch.manual_seed(0)
    policy = FormationDiffusionPolicy(nearest_config()).eval()
    replanner = Replanner.from_config(policy.config, policy_sampler(policy), ReplanExperiment(blend_steps=3))
    env = _env_state([])
    stacked = {k: v[:, None].repeat(1, N_OBS, 1) for k, v in _batch(env).items()}
    noise = torch.randn(2, HORIZON, 2, generator=torch.Generator().manual_seed(3))
    replanner.start(1)
    for _ in range(policy.config.n_action_steps):
        last = replanner.act(env, lambda rows: stacked, noise=noise[:1])
    raw = policy.sample_action_chunks(stacked, 1, noise=noise[1:])[:, 0]
    first = replanner.act(env, lambda rows: stacked, noise=noise[1:])
    torch.testing.assert_close(first, raw[:, 0] + 0.75 * (last - raw[:, 0]))
    assert replanner.stats["replans"] == 2


def test_route_encoding_policy_scores_chunks_on_its_nearest_part(monkeypatch):
    """A 'nearest+route' policy decodes the same obstacles as a 'nearest' one (the route values after
    the rows are not obstacles), so best-of-K keeps the same chunk (route pursuit's proposal, which
    only the route hint gives, left out)."""
    monkeypatch.setattr(safety_layer, "ROUTE_PROPOSAL", False)
    inputs, outputs = formation_features(env_dim=55)
    route = FormationDiffusionPolicy(
        nearest_config(input_features=inputs, output_features=outputs, obstacle_encoding="nearest+route")
    ).eval()
    plain = FormationDiffusionPolicy(nearest_config()).eval()
    obs = np.array([[[0.5, 1.0, 0.3], [-0.5, 1.0, 0.3], [2.0, 3.0, 0.5]]])  # ahead of both leaders
    pose, goal = np.array([[0.0, 0.0, np.pi / 2]]), np.array([[0.0, 8.0]])
    env55 = environment_state(obs, obs[..., 2] > 0, goal, "nearest+route", pose=pose)
    env50 = environment_state(obs, obs[..., 2] > 0, goal, "nearest", pose=pose)
    assert env55.shape == (1, 55)
    straight = np.tile([0.5, 0.0], (1, 1, HORIZON, 1))  # into the first obstacle
    turn = np.tile([0.3, 1.0], (1, 1, HORIZON, 1))
    chunks = np.concatenate([straight, turn], axis=1)
    kept55, info55 = route.replanner.layer.choose(env55, chunks)
    kept50, info50 = plain.replanner.layer.choose(env50, chunks)
    np.testing.assert_array_equal(kept55, kept50)
    np.testing.assert_array_equal(info55["safe"], info50["safe"])
    assert not info55["safe"][0, 0]  # the straight chunk hits the obstacle ahead


def test_route_proposal_is_kept_when_no_sampled_chunk_is_safe(monkeypatch):
    """With a route hint best-of-K scores route pursuit's chunk beside the sampled ones
    (``ROUTE_PROPOSAL``): obstacles ahead of both leaders, every sampled chunk drives straight into
    them, the hint's route turns left, so the proposal (index K) is kept. Without a route hint there
    is no proposal, and nothing to refuse."""
    monkeypatch.setattr(safety_layer, "FOLLOWER_MARGIN", 0.0)  # the proposal grazes with the allowance
    inputs, outputs = formation_features(env_dim=55)
    kw = dict(input_features=inputs, output_features=outputs, obstacle_encoding="nearest+route")
    obs = np.array([[[0.5, 1.2, 0.3], [-0.5, 1.2, 0.3]]])
    pose, goal = np.array([[0.0, 0.0, np.pi / 2]]), np.array([[-6.0, 6.0]])
    env = environment_state(obs, obs[..., 2] > 0, goal, "nearest+route", pose=pose)
    chunks = np.tile([0.6, 0.0], (1, 3, HORIZON, 1))
    kept = {}
    for proposal in (False, True):
        monkeypatch.setattr(safety_layer, "ROUTE_PROPOSAL", proposal)
        policy = FormationDiffusionPolicy(nearest_config(**kw)).eval()
        kept[proposal], info = policy.replanner.layer.choose(env, chunks)
        assert not info["safe"][0, :3].any() and info["safe"].shape[1] == 3 + proposal
        assert info["proposal_kept"][0] == proposal
    assert kept[True][0, 0, 1] > 0  # it turns left, down the route
    plain = FormationDiffusionPolicy(nearest_config(num_candidates=2, safety_horizon=20)).eval()
    nearest = environment_state(obs, obs[..., 2] > 0, goal, "nearest", pose=pose)
    _, info = plain.replanner.layer.choose(nearest, chunks)
    assert info["safe"].shape[1] == 3 and not info["proposal_kept"].any()


def _route_proposal_config(**fields) -> dict:
    """Config keywords of a ``nearest+route`` policy (route pursuit's proposal joins best-of-K's
    candidates), and ``fields``."""
    inputs, outputs = formation_features(env_dim=55)
    return dict(input_features=inputs, output_features=outputs, obstacle_encoding="nearest+route", **fields)


def test_route_proposal_blending_enters_from_the_executed_action(monkeypatch):
    """With ``PROPOSAL_BLEND`` m route pursuit's proposal starts from the last executed action
    (``core.safety.replan_blend``): its first action lies 1 / (m + 1) of the step from it, its actions from the
    m-th on are unchanged; without a last action (an episode's first chunk), or with a rate-limited
    actuator, it is left as computed."""
    assert safety_layer.PROPOSAL_BLEND == 4  # the shipped layer's
    monkeypatch.setattr(safety_layer, "FOLLOWER_MARGIN", 0.0)  # the proposal grazes with the allowance
    kw = _route_proposal_config()
    obs = np.array([[[0.5, 1.2, 0.3], [-0.5, 1.2, 0.3]]])
    pose, goal = np.array([[0.0, 0.0, np.pi / 2]]), np.array([[-6.0, 6.0]])
    env = environment_state(obs, obs[..., 2] > 0, goal, "nearest+route", pose=pose)
    chunks = np.tile([0.6, 0.0], (1, 3, HORIZON, 1))  # every sample drives into the obstacles
    last = np.array([[0.1, 0.0]])
    plain, _ = FormationDiffusionPolicy(nearest_config(**kw)).eval().replanner.layer.choose(env, chunks)
    monkeypatch.setattr(safety_layer, "PROPOSAL_BLEND", 3)
    policy = FormationDiffusionPolicy(nearest_config(**kw)).eval()
    kept, info = policy.replanner.layer.choose(env, chunks, last, np.array([True]))
    assert info["proposal_kept"][0]
    np.testing.assert_allclose(kept[0, 0], plain[0, 0] + 0.75 * (last[0] - plain[0, 0]))
    np.testing.assert_allclose(kept[0, 3:], plain[0, 3:])
    first, _ = policy.replanner.layer.choose(env, chunks, last, np.array([False]))
    np.testing.assert_allclose(first, plain)
    # a rate-limited actuator ramps the step itself: the proposal is left as computed
    limited = FormationDiffusionPolicy(
        nearest_config(safety_world=KnownWorld(max_linear_accel=0.5), **kw)
    ).eval()
    as_computed, _ = limited.replanner.layer.choose(env, chunks, last, np.array([True]))
    np.testing.assert_allclose(as_computed, plain)


def test_the_follower_margin_widens_only_the_followers(monkeypatch):
    """``FOLLOWER_MARGIN``: the followers' discs are checked that much larger, not where the layer
    predicts moving obstacles; the filter's barrier sees the allowance."""
    from lerobot_formation.core.safety.layer import SafetyLayer, SafetySettings, safety_geometry

    def layer(config) -> SafetyLayer:
        return SafetyLayer(SafetySettings.from_config(config), encoding=config.obstacle_encoding)

    _, _, radius = safety_geometry()
    policy = FormationDiffusionPolicy(nearest_config(num_candidates=2))
    np.testing.assert_allclose(
        policy.replanner.layer.agent_radii, [radius, radius, radius + 0.03, radius + 0.03]
    )
    movers = nearest_config(num_candidates=2, safety_world=KnownWorld(moving_obstacles=True))
    assert layer(movers).agent_radii == radius  # room to dodge a mover
    # a turn that swings the right follower (template (0.5, -1)) at an obstacle h = 0.53 m from its
    # disc: the barrier (alpha = 2) lets it approach at up to 2 h, which 1 rad/s keeps to without the
    # allowance; with a 5 cm allowance h is 0.48 m and the filter slows the turn
    monkeypatch.setattr(safety_layer, "CBF_RATE", 2.0)
    beside_follower = _env_state([[0.5 + radius + 0.3 + 0.53, -1.0, 0.3]])
    turn = np.array([[0.0, 1.0]])
    config = nearest_config(safety_filter="cbf", safety_margin=0.0)
    monkeypatch.setattr(safety_layer, "FOLLOWER_MARGIN", 0.0)
    plain = layer(config)
    monkeypatch.setattr(safety_layer, "FOLLOWER_MARGIN", 0.05)
    wide = layer(config)
    assert not plain.filter(beside_follower.numpy(), turn)[1][0]
    slowed, changed = wide.filter(beside_follower.numpy(), turn)
    assert changed[0] and 0.0 < slowed[0, 1] < 1.0


def test_the_horizon_is_checked_with_its_value():
    for bad in (-3, 2.5, True):
        with pytest.raises(
            ValueError, match=rf"safety_horizon must be an integer >= 0 \[steps\], got {bad!r}"
        ):
            nearest_config(safety_horizon=bad)
    # without a route hint there is no route pursuit to follow a chunk: the horizon is the halt's alone
    assert nearest_config(num_candidates=2, safety_horizon=20).safety_horizon == 20


def test_progress_grid_reaches_the_scorer(monkeypatch):
    """``SafetyLayer.choose`` scores progress on the shipped layer's grid: ``PROGRESS_RESOLUTION``
    cells, read bilinearly."""
    from lerobot_formation.core.safety import filters as safety
    from lerobot_formation.core.safety.layer import PROGRESS_RESOLUTION

    seen = []
    real = safety.cost_to_go_progress

    def spy(*args):
        seen.append(args[4:])
        return real(*args)

    monkeypatch.setattr(safety, "cost_to_go_progress", spy)
    env = _env_state([])
    chunks = np.tile([0.5, 0.0], (1, 2, HORIZON - N_OBS + 1, 1))
    FormationDiffusionPolicy(nearest_config(num_candidates=2)).eval().replanner.layer.choose(env, chunks)
    assert seen == [(PROGRESS_RESOLUTION, True)] and PROGRESS_RESOLUTION == 0.4


def test_coherence_keeps_the_sample_closest_to_the_plan_being_replaced(monkeypatch):
    """``SafetyLayer.choose`` with the rest of the previous plan: a large weight (``COHERENCE``) keeps the left arc it
    continues over the straight chunk that makes more progress; without a previous plan, progress
    decides. Through ``select_action`` every replan after the first hands the scorer the plan it
    replaces, from the current step on (here n_action_steps = 8 of them)."""
    from lerobot_formation.core.safety import filters as safety

    env = _env_state([])
    straight = np.tile([0.5, 0.0], (1, 1, HORIZON - N_OBS + 1, 1))
    arc = np.tile([0.5, 0.3], (1, 1, HORIZON - N_OBS + 1, 1))
    chunks = np.concatenate([straight, arc], axis=1)
    monkeypatch.setattr(safety_layer, "COHERENCE", 10.0)
    policy = FormationDiffusionPolicy(nearest_config(num_candidates=2)).eval()
    previous = np.tile([0.5, 0.3], (1, 8, 1))
    kept, info = policy.replanner.layer.choose(env, chunks, np.zeros((1, 2)), np.array([True]), previous)
    assert info["choice"][0] == 1
    kept, info = policy.replanner.layer.choose(env, chunks)
    assert info["choice"][0] == 0

    seen = []
    real = safety.select_chunk

    def spy(*args, **kwargs):
        seen.append(kwargs.get("coherence"))
        return real(*args, **kwargs)

    monkeypatch.setattr(safety, "select_chunk", spy)
    torch.manual_seed(0)
    policy.reset()
    for _ in range(20):
        policy.select_action(_batch(env))
    assert len(seen) >= 3
    first, later = seen[0], seen[1:]
    assert not first.keep_to.any()  # the first replan has no plan to keep to
    for c in later:
        assert c.previous.shape == (1, 8, 2) and c.keep_to.all() and c.weight == 10.0
        assert np.allclose(c.ranges, np.array(policy.config.action_high) - np.array(policy.config.action_low))


def test_coherence_does_not_keep_to_a_plan_the_filter_cut_short(monkeypatch):
    """A replan after a plan the filter cut short (an intervention marks it used up, as
    here by hand after 3 of its 8 actions) gets no coherence preference: that plan met a barrier. The
    replan after a plan that ran its ``n_action_steps`` does."""
    from lerobot_formation.core.safety import filters as safety

    env = _env_state([])
    kept_to = []
    real = safety.select_chunk

    def spy(*args, **kwargs):
        kept_to.append(bool(kwargs["coherence"].keep_to[0]))
        return real(*args, **kwargs)

    monkeypatch.setattr(safety, "select_chunk", spy)
    torch.manual_seed(0)
    policy = FormationDiffusionPolicy(nearest_config(num_candidates=4)).eval()  # COHERENCE 1
    for _ in range(3):
        policy.select_action(_batch(env))
    policy.replanner.plan_pos[:] = policy.config.n_action_steps  # what an intervention does
    for _ in range(9):
        policy.select_action(_batch(env))
    assert kept_to == [False, False, True]  # the first replan, the cut one, the full one


def test_a_warm_start_skips_the_first_denoiser_calls_of_every_candidate():
    """Through ``select_action``: after the first replan (nothing to continue yet: K cold rows, every
    step), a replan with warm start j warm-starts all K candidates (the first j calls are not made)."""
    K, j = 4, 1
    config = nearest_config(num_candidates=K, warm_start_step=j, inference_backend="lean")
    policy = FormationDiffusionPolicy(config).eval()
    rows = []
    policy.inference_model.unet.register_forward_hook(lambda module, args, out: rows.append(len(args[0])))
    env = _env_state([])
    torch.manual_seed(0)
    policy.reset()
    policy.select_action(_batch(env))  # the first replan
    assert rows == [K] * config.num_inference_steps
    rows.clear()
    for _ in range(config.n_action_steps):  # runs its chunk, then replans from its rest
        policy.select_action(_batch(env))
    later = config.num_inference_steps - j
    assert rows == [K] * later


@pytest.mark.parametrize("K", [1, 3])
def test_chunk_smoothing_smooths_every_sample_from_the_executed_command(monkeypatch, K):
    """``chunk_smoothing`` n: every sampled chunk is smoothed (``core.safety.replan_blend.smooth_chunks``)
    before best-of-K scores it, with K = 1 too: the first chunk from its own first command, a later one
    entered from the command executed last. Open road: every candidate is safe and the plan kept is one
    of the smoothed samples."""
    n = 2
    config = nearest_config(num_candidates=K, chunk_smoothing=n)
    policy = FormationDiffusionPolicy(config).eval()
    T = config.horizon - config.n_obs_steps + 1
    drawn = []

    def sample(stacked, k, **kwargs):
        chunk = torch.rand(1, k, T, 2, generator=torch.Generator().manual_seed(len(drawn))) * 0.5
        drawn.append(chunk)
        return chunk

    monkeypatch.setattr(policy, "sample_action_chunks", sample)
    env = _env_state([])
    policy.reset()
    policy.select_action(_batch(env))
    replanner = policy.replanner
    first = smooth_chunks(drawn[0], torch.zeros(1, 2), torch.zeros(1, dtype=torch.bool), n)
    assert any(torch.allclose(replanner.plan[0], first[0, k]) for k in range(K))
    for _ in range(config.n_action_steps - 1):
        policy.select_action(_batch(env))
    last = replanner.last_action.clone()
    policy.select_action(_batch(env))  # the second replan
    second = smooth_chunks(drawn[1], last, torch.ones(1, dtype=torch.bool), n)
    assert any(torch.allclose(replanner.plan[0], second[0, k]) for k in range(K))
    assert not any(torch.allclose(replanner.plan[0], drawn[1][0, k]) for k in range(K))


def test_chunk_smoothing_is_checked_with_its_value():
    for bad in (-1, 1.5, True, "2"):
        with pytest.raises(
            ValueError, match=rf"chunk_smoothing must be an integer >= 0 \[passes\], got {bad!r}"
        ):
            nearest_config(chunk_smoothing=bad)
    assert nearest_config(chunk_smoothing=3).chunk_smoothing == 3


def test_chunk_smoothing_smooths_the_blended_route_proposal_too(monkeypatch):
    """Where route pursuit's proposal is blended in (``PROPOSAL_BLEND``), the replanner's
    ``chunk_smoothing`` smooths it after the blend, as it does the sampled chunks; under a
    rate-limited actuator (no blend) it is left as computed."""
    monkeypatch.setattr(safety_layer, "PROPOSAL_BLEND", 3)
    kw = _route_proposal_config()
    obs = np.array([[[5.0, -5.0, 0.3]]])  # far off the way to the goal
    pose, goal = np.array([[0.0, 0.0, np.pi / 2]]), np.array([[-6.0, 6.0]])
    env = environment_state(obs, obs[..., 2] > 0, goal, "nearest+route", pose=pose)
    chunks = np.zeros((1, 3, HORIZON, 2))  # every sample stands still: the proposal makes the progress
    last, had = np.array([[0.1, 0.0]]), np.array([True])
    blended, _ = (
        FormationDiffusionPolicy(nearest_config(**kw)).eval().replanner.layer.choose(env, chunks, last, had)
    )
    replanner = FormationDiffusionPolicy(nearest_config(chunk_smoothing=2, **kw)).eval().replanner
    n = replanner.settings.chunk_smoothing
    kept, info = replanner.layer.choose(env, chunks, last, had, chunk_smoothing=n)
    assert info["proposal_kept"][0]
    np.testing.assert_allclose(kept, smooth_chunks(blended, last, had, 2))
    assert not np.allclose(kept, blended)
    limited = dict(kw, safety_world=KnownWorld(max_linear_accel=0.5))
    plain, _ = (
        FormationDiffusionPolicy(nearest_config(**limited))
        .eval()
        .replanner.layer.choose(env, chunks, last, had)
    )
    as_computed, _ = (
        FormationDiffusionPolicy(nearest_config(chunk_smoothing=2, **limited))
        .eval()
        .replanner.layer.choose(env, chunks, last, had, chunk_smoothing=2)
    )
    np.testing.assert_allclose(as_computed, plain)


def test_layer_without_samples_runs_route_pursuit_under_the_check_and_never_calls_the_network(monkeypatch):
    """``ReplanExperiment(sampled=False)`` (the "route-pursuit-safe" baseline): the network samples
    nothing; on an open field the kept chunk is route pursuit's proposal (every replan keeps it), and
    with obstacles across the route an escape or the proposal, never a sample. It needs the proposal
    (a route hint) and a layer."""
    from lerobot_formation.core.controllers.route_pursuit import pursuit_chunk
    from lerobot_formation.core.safety.layer import safety_geometry
    from lerobot_formation.policy.replanner import ReplanExperiment, Replanner, policy_sampler

    kw = _route_proposal_config(num_candidates=4, safety_filter="cbf")
    policy = FormationDiffusionPolicy(nearest_config(**kw)).eval()

    def no_sampling(*args, **kwargs):
        raise AssertionError("the network was sampled")

    monkeypatch.setattr(policy, "sample_action_chunks", no_sampling)
    replanner = Replanner.from_config(policy.config, policy_sampler(policy), ReplanExperiment(sampled=False))
    pose, goal = np.array([[0.0, 0.0, np.pi / 2]]), np.array([[-6.0, 6.0]])
    free = np.array([[[FAR, FAR, 0.0]]])
    env = torch.from_numpy(
        environment_state(free, free[..., 2] > 0, goal, "nearest+route", pose=pose)
    ).float()
    replanner.start(1)
    actions = [replanner.act(env, lambda rows: None) for _ in range(3)]
    view = replanner.layer.observed_obstacles(env.numpy())
    _, dt, _ = safety_geometry()
    proposal = pursuit_chunk(view.route, view.goal, replanner.chunk_length, dt, policy.config.action_high[1])
    raw = policy.unnormalize_action(torch.stack(actions, 1)).numpy()
    np.testing.assert_allclose(raw[0], proposal[0, :3], atol=1e-5)
    assert replanner.stats["replans"] == replanner.stats["proposals"] == 1

    # obstacles across the route, close: every replan keeps the proposal or an escape
    blocked = np.array([[[0.0, 0.9, 0.4], [-0.9, 0.9, 0.4], [0.9, 0.9, 0.4]]])
    env = environment_state(blocked, blocked[..., 2] > 0, goal, "nearest+route", pose=pose)
    replanner.reset(1)
    for _ in range(6):
        replanner.act(torch.from_numpy(env).float(), lambda rows: None)
    stats = replanner.stats
    assert stats["escapes"] > 0
    assert stats["proposals"] + stats["escapes"] + stats["stops"] + stats["searched"] == stats["replans"]

    alone = ReplanExperiment(sampled=False)
    with pytest.raises(ValueError, match=r"samples nothing.*obstacle_encoding='nearest', num_candidates=4"):
        Replanner.from_config(  # a layer (K = 4), but no route hint: no proposal
            nearest_config(num_candidates=4, safety_filter="none"), experiment=alone
        )
    with pytest.raises(ValueError, match=r"samples nothing.*num_candidates=1, safety_filter='none'"):
        Replanner.from_config(nearest_config(**_route_proposal_config()), experiment=alone)


def test_route_pursuit_safe_is_a_controller_that_needs_no_checkpoint():
    from lerobot_formation.bench.controllers import controller_names, needs_policy

    assert "route-pursuit-safe" in controller_names()
    assert not needs_policy("route-pursuit-safe") and not needs_policy("route-pursuit")


def test_bench_runs_route_pursuit_safe_without_a_checkpoint(tmp_path, monkeypatch):
    """``lerobot-formation-bench --controllers route-pursuit-safe`` on a level with moving obstacles,
    no ``--policy.path``: the shipped default's layer settings, nothing sampled, the layer's counts
    reported."""
    import json

    from lerobot_formation.bench import cli

    def no_sampling(*args, **kwargs):
        raise AssertionError("the network was sampled")

    monkeypatch.setattr(FormationDiffusionPolicy, "sample_action_chunks", no_sampling)
    out = tmp_path / "out"
    argv = ["--controllers", "route-pursuit-safe", "--scenes", "level5:2"]
    assert (
        cli.main(
            [*argv, "--candidates", "4", "--threads", "1", "--no-figures", "--no-progress", "--out", str(out)]
        )
        == 0
    )
    res = json.loads((out / "results.json").read_text())["route-pursuit-safe"]
    assert res["n_episodes"] == 2
    safety = res["safety"]
    assert (
        safety["replans"] > 0
        and safety["proposals"] + safety["escapes"] + safety["stops"] + safety["searched"]
        == safety["replans"]
    )


def test_sampling_guidance_is_checked_with_its_value():
    for bad in (-1.0, True):
        with pytest.raises(ValueError, match=f"sampling_guidance must be a finite step >= 0.*{bad!r}"):
            nearest_config(sampling_guidance=bad, inference_backend="lean")
    with pytest.raises(ValueError, match="must be finite numbers, got sampling_guidance=nan"):
        nearest_config(sampling_guidance=float("nan"), inference_backend="lean")
    with pytest.raises(ValueError, match="sampling_guidance > 0 runs in the lean and trace samplers"):
        nearest_config(sampling_guidance=1.0)  # the eager backend is LeRobot's own sampler
    with pytest.raises(ValueError, match="needs an egocentric obstacle encoding"):
        tiny_config(sampling_guidance=1.0, inference_backend="lean")  # guidance reads the obstacles
    assert nearest_config(sampling_guidance=1.0, inference_backend="lean").safety_layer


def test_guided_sampling_keeps_a_chunk_further_from_the_obstacle_than_the_same_noise_unguided(monkeypatch):
    """K = 1, no filter: with ``sampling_guidance`` the sample itself is moved away from the observed
    obstacle (the footprint's predicted clearance grows) against the same network's sample from the
    same noise without it."""
    from lerobot_formation.core.controllers.footprint import TeamBody, sequence_clearance
    from lerobot_formation.core.safety import layer as safety_layer
    from lerobot_formation.core.safety.layer import safety_geometry

    monkeypatch.setattr(safety_layer, "GUIDANCE_DISTANCE", 0.5)
    template, dt, radius = safety_geometry()
    body = TeamBody(template, radius, dt)
    obstacle = [0.0, 1.0, 0.4]  # straight ahead of the midpoint
    env = _env_state([obstacle])
    noise = torch.randn(1, HORIZON, 2, generator=torch.Generator().manual_seed(5))
    torch.manual_seed(0)
    plain = FormationDiffusionPolicy(nearest_config(inference_backend="lean")).eval()
    guided = FormationDiffusionPolicy(nearest_config(inference_backend="lean", sampling_guidance=5.0)).eval()
    guided.load_state_dict(plain.state_dict())
    stacked = {k: v[:, None].repeat(1, N_OBS, 1) for k, v in _batch(env).items()}
    unguided = plain.sample_action_chunks(stacked, 1, noise=noise.clone())[:, 0]
    guided.reset()
    guided.select_action(_batch(env), noise=noise.clone())  # the first replan: the same history
    pose = np.array([[0.0, 0.0, np.pi / 2]])

    def clearance(chunk):
        actions = guided.unnormalize_action(chunk)[None].numpy().astype(np.float64)
        return float(sequence_clearance(pose, actions, np.array([[obstacle]]), body)[0][0, 0])

    assert clearance(guided.replanner.plan) > clearance(unguided) + 0.05
    assert guided.replanner.stats["replans"] == 1 and guided.replanner.stats["filter_interventions"] == 0


def test_guided_route_pursuit_moves_the_proposal_away_from_the_obstacle_and_never_samples(monkeypatch):
    """``ReplanExperiment(sampled=False)`` at K = 1 with ``sampling_guidance`` (the "route-pursuit-guided"
    baseline): the plan is route pursuit's chunk moved by the clearance guidance
    ``num_inference_steps`` times (``PlanSettings.denoising_steps``), with no best-of-K; it keeps more clearance from an obstacle beside
    the route than route pursuit's own chunk, and equals that chunk where no obstacle is within the
    guidance distance."""
    from lerobot_formation.core.controllers.footprint import TeamBody, sequence_clearance
    from lerobot_formation.core.controllers.route_pursuit import pursuit_chunk
    from lerobot_formation.core.safety import layer as safety_layer
    from lerobot_formation.core.safety.layer import safety_geometry
    from lerobot_formation.policy.replanner import ReplanExperiment, Replanner, policy_sampler

    monkeypatch.setattr(safety_layer, "GUIDANCE_DISTANCE", 0.5)
    kw = _route_proposal_config(inference_backend="lean", sampling_guidance=2.0)
    policy = FormationDiffusionPolicy(nearest_config(**kw)).eval()

    def no_sampling(*args, **kwargs):
        raise AssertionError("the network was sampled")

    monkeypatch.setattr(policy, "sample_action_chunks", no_sampling)
    replanner = Replanner.from_config(policy.config, policy_sampler(policy), ReplanExperiment(sampled=False))
    assert not replanner.best_of
    template, dt, radius = safety_geometry()
    body = TeamBody(template, radius, dt)
    pose, goal = np.array([[0.0, 0.0, np.pi / 2]]), np.array([[0.0, 6.0]])

    def plan_and_proposal(obstacles):
        obstacles = np.array([obstacles])
        env = torch.from_numpy(
            environment_state(obstacles, obstacles[..., 2] > 0, goal, "nearest+route", pose=pose)
        ).float()
        replanner.reset(1)
        replanner.act(env, lambda rows: None)
        view = replanner.layer.observed_obstacles(env.numpy())
        proposal = pursuit_chunk(
            view.route, view.goal, replanner.chunk_length, dt, policy.config.action_high[1]
        )
        return policy.unnormalize_action(replanner.plan).numpy().astype(np.float64), proposal, view

    plan, proposal, _ = plan_and_proposal([[FAR, FAR, 0.0]])
    np.testing.assert_allclose(plan, proposal, atol=1e-5)  # nothing within the guidance distance

    obstacle = [0.75, 1.2, 0.3]  # right of the straight route, within 0.5 m of the right-hand agents
    plan, proposal, view = plan_and_proposal([obstacle])
    midpoint = np.array([[[0.0, 0.0, np.pi / 2]]])[0]

    def clearance(actions):
        return float(sequence_clearance(midpoint, actions[None], view.obstacles, body)[0][0, 0])

    assert clearance(plan) > clearance(proposal) + 0.02
    assert replanner.stats["replans"] == 1 and replanner.stats["proposals"] == 0


def test_bench_runs_route_pursuit_guided_without_a_checkpoint(tmp_path, monkeypatch):
    """``--controllers route-pursuit-guided`` on a level with moving obstacles, no ``--policy.path``:
    the shipped default's guidance moves route pursuit's chunk, one per replan, nothing sampled."""
    import json

    from lerobot_formation.bench import cli
    from lerobot_formation.bench.controllers import needs_policy

    def no_sampling(*args, **kwargs):
        raise AssertionError("the network was sampled")

    assert not needs_policy("route-pursuit-guided")
    monkeypatch.setattr(FormationDiffusionPolicy, "sample_action_chunks", no_sampling)
    out = tmp_path / "out"
    argv = ["--controllers", "route-pursuit-guided", "--scenes", "level5:2"]
    assert cli.main([*argv, "--threads", "1", "--no-figures", "--no-progress", "--out", str(out)]) == 0
    res = json.loads((out / "results.json").read_text())["route-pursuit-guided"]
    assert res["n_episodes"] == 2
    assert res["safety"]["replans"] > 0 and res["safety"]["proposals"] == res["safety"]["escapes"] == 0
