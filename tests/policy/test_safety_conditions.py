"""The safety layer under realistic conditions: moving obstacles, a known actuator delay and rate
limits, sensing noise (the config's ``safety_world``, a ``KnownWorld``), their defaults, and the
bench's wiring and reports."""

import dataclasses
import importlib.util
from pathlib import Path

import numpy as np
import pytest
import torch
from plugin_helpers import formation_features, nearest_config, save_nearest_checkpoint

from lerobot_formation.core.encodings.obstacle_grid import environment_state, environment_state_dim
from lerobot_formation.core.safety.layer import KnownWorld
from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy
from lerobot_formation.policy.replanner import Replanner

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


def _reference_module():
    spec = importlib.util.spec_from_file_location(
        "make_safety_off_reference", FIXTURES / "make_safety_off_reference.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _told(**world) -> dict:
    """The config field of a layer told ``world`` (``KnownWorld``'s fields)."""
    return {"safety_world": KnownWorld(**world)}


def _policy(**overrides):
    torch.manual_seed(0)
    return FormationDiffusionPolicy(nearest_config(num_candidates=4, safety_filter="cbf", **overrides)).eval()


def test_with_the_new_settings_off_the_replanner_acts_as_before():
    """Bit for bit the actions and counts of the fixture (``make_safety_off_reference.py``: the layer
    with the conditions' settings off), in a closed loop with best-of-4, escapes and the filter at
    work."""
    ref = _reference_module()
    want = np.load(FIXTURES / "safety_off_reference.npz")
    got = ref.closed_loop(_policy())
    np.testing.assert_array_equal(got["actions"], want["actions"])
    np.testing.assert_array_equal(got["stats"], want["stats"])
    assert want["stats"][ref.STAT_NAMES.index("filter_interventions")] > 0
    assert want["stats"][ref.STAT_NAMES.index("escapes")] > 0
    # the settings change what happens (so the comparison above can fail)
    late = ref.closed_loop(_policy(**_told(action_delay=2, max_linear_accel=0.5)))
    assert not np.array_equal(late["actions"], want["actions"])


def test_safety_settings_are_checked_with_their_value():
    """The config's own fields here; ``safety_world``'s where a ``KnownWorld`` is made
    (``tests/core/safety/test_layer.py``)."""
    for bad, message in (
        (dict(safety_horizon=-1), r"safety_horizon must be an integer >= 0 \[steps\], got -1"),
        (dict(safety_horizon=1.5), r"safety_horizon must be an integer >= 0 \[steps\], got 1.5"),
        (dict(safety_margin=-0.1), r"safety_margin must be a number >= 0 \[m\], got -0.1"),
        (
            dict(safety_mover_uncertainty=-0.05),
            r"safety_mover_uncertainty must be a number >= 0 \[m/s\], got -0.05",
        ),
        (
            dict(safety_world={"action_delay": 1}),
            r"safety_world must be a KnownWorld \(core.safety.layer\), got \{'action_delay': 1\}",
        ),
    ):
        with pytest.raises(ValueError, match=message):
            nearest_config(**bad)
    with pytest.raises(ValueError, match=r"safety_world.action_delay must be an integer >= 0"):
        nearest_config(**_told(action_delay=-1))


def test_the_layer_smooths_its_view_when_it_knows_the_sensing_noise():
    """With a noise std in the config the replanner's view of the obstacles is smoothed over the
    steps (``core.perception.obstacle_filter``); with exact sensing it is the observation itself."""
    exact = _policy(safety_margin=0.05).replanner
    noisy = _policy(safety_margin=0.05, **_told(obstacle_noise=0.02, pose_noise=0.02)).replanner
    exact.start(1), noisy.start(1)
    assert exact.layer.smoother is None and noisy.layer.smoother is not None

    def observed(x):
        return torch.from_numpy(
            environment_state(
                np.array([[[x, 2.0, 0.3]]]),
                np.ones((1, 1), bool),
                np.array([[0.0, 8.0]]),
                "nearest",
                pose=np.array([[0.0, 0.0, np.pi / 2]]),
            )
        )

    rows = torch.tensor([0])
    for replanner in (exact, noisy):
        replanner.view(observed(1.0), rows)
    assert exact.view(observed(1.2), rows).obstacles[0, 0, 0] == pytest.approx(1.2)
    smoothed = noisy.view(observed(1.2), rows).obstacles[0, 0, 0]
    assert 1.0 < smoothed < 1.2  # a step toward the new draw, not all the way


def test_the_replanner_keeps_the_commands_in_flight_and_predicts_the_start():
    """With a delay of 2 the replanner remembers its last two commands (physical, oldest first), and
    the start of the next command is the pose after them, as the actuator model runs them."""
    policy = _policy(**_told(action_delay=2, max_linear_accel=0.5, max_angular_accel=2.0))
    replanner = Replanner.from_config(policy.config, _reference_module().stand_in_sampler(policy))
    replanner.start(1)
    env = torch.from_numpy(
        environment_state(
            np.array([[[3.0, 3.0, 0.3]]]),
            np.ones((1, 1), bool),
            np.array([[0.0, 8.0]]),
            "nearest",
            pose=np.array([[0.0, 0.0, np.pi / 2]]),
        )
    )

    def noise(rows, K):  # the engine's contract: K candidates for each episode of ``rows``
        n = len(rows) * K
        return torch.randn(n, policy.config.horizon, 2, generator=torch.Generator().manual_seed(n))

    sent = []
    for _ in range(5):
        a = replanner.act(env, lambda rows: {}, noise=noise)
        sent.append(np.clip(policy.unnormalize_action(a).numpy(), [0.0, -1.5], [0.6, 1.5])[0])
    layer = replanner.layer
    np.testing.assert_allclose(layer.in_flight[0], sent[-2:], atol=1e-6)
    # the actuator model ran the first three commands from rest, rate limited: 0.05 m/s per step
    assert 0 < layer.executed_velocity[0, 0] <= 0.15 + 1e-9
    view = replanner.view(env, torch.tensor([0]))
    assert view.start.steps == 2 and view.start.pose[0, 1] > 0  # ahead of where the team is now
    replanner.start(1)  # a new episode: nothing in flight, at rest
    assert not layer.in_flight.any() and not layer.executed_velocity.any()


def _velocity_layer(encoding: str):
    """The safety layer of a best-of-4 policy of ``encoding`` that predicts moving obstacles."""
    inputs, outputs = formation_features(env_dim=environment_state_dim(encoding))
    config = nearest_config(
        input_features=inputs,
        output_features=outputs,
        obstacle_encoding=encoding,
        num_candidates=4,
        **_told(moving_obstacles=True),
    )
    return FormationDiffusionPolicy(config).replanner.layer


def test_moving_obstacle_velocities_from_the_encoding_or_the_tracker():
    """A "nearest+velocity" policy reads the obstacles' velocities from its observation; a "nearest"
    one gets them from its tracker (new per episode); without ``moving_obstacles`` neither."""
    obstacles = np.array([[[1.0, 2.0, 0.3], [-2.0, 4.0, 0.5], [2.0, 5.0, 0.4], [-1.0, 6.5, 0.6]]])
    velocity = np.zeros((1, 4, 2))
    velocity[0, 0] = [0.3, 0.0]
    goal, pose = np.array([[0.0, 8.0]]), np.array([[0.0, 0.0, np.pi]])  # facing -x: body axes turned
    mask = np.ones((1, 4), bool)
    seeing = _velocity_layer("nearest+velocity")
    env = environment_state(obstacles, mask, goal, "nearest+velocity", pose=pose, obstacle_velocity=velocity)
    view = seeing.observed_obstacles(env)
    near = np.argmin(np.abs(view.obstacles[0, :, 2] - 0.3))  # the 0.3 m obstacle's slot
    np.testing.assert_allclose(view.velocity[0, near], [0.0, -0.3], atol=1e-6)  # body x right, y ahead
    assert view.velocity[0, ~view.mask[0]].sum() == 0 and seeing.observed_obstacles(env).velocity is not None

    # "nearest+route+velocity": the same velocities, then the route hint's carrots after them
    both = _velocity_layer("nearest+route+velocity").observed_obstacles(
        environment_state(
            obstacles, mask, goal, "nearest+route+velocity", pose=pose, obstacle_velocity=velocity
        )
    )
    route = environment_state(obstacles, mask, goal, "nearest+route", pose=pose)[:, 50:54]
    np.testing.assert_allclose(both.velocity, view.velocity)
    np.testing.assert_allclose(both.route, route)

    tracking = _policy(**_told(moving_obstacles=True)).replanner
    tracking.start(1)
    assert tracking.layer.tracker is not None
    for t in range(12):
        moved = obstacles.copy()
        moved[..., :2] += velocity * 0.1 * t
        env = torch.from_numpy(environment_state(moved, mask, goal, "nearest", pose=pose))
        view = tracking.view(env, torch.tensor([0]))
    near = np.argmin(np.abs(view.obstacles[0, :, 2] - 0.3))
    np.testing.assert_allclose(view.velocity[0, near], [0.0, -0.3], atol=0.05)
    tracking.start(1)
    assert not tracking.layer.tracker.started.any()  # a new episode, new tracks
    assert _policy().replanner.layer.observed_obstacles(env.numpy()).velocity is None
    plain = _policy().replanner
    plain.start(1)
    assert plain.layer.tracker is None


def test_mover_settings_reach_best_of_k(monkeypatch):
    """``safety_mover_uncertainty`` and (with the world's ``moving_obstacles`` only)
    ``safety_horizon`` as the halt lookahead are what ``select_chunk`` gets, beside the shipped layer's wired
    settings: the escape lattice of ``ESCAPE_SPEEDS`` and the widest of every candidate scored as the
    fallback."""
    from lerobot_formation.core.safety import filters as safety
    from lerobot_formation.core.safety.layer import ESCAPE_SPEEDS

    seen = {}
    real = safety.select_chunk

    def spy(*args, **kwargs):
        seen.update(kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr(safety, "select_chunk", spy)
    obstacles = np.array([[[1.0, 2.0, 0.3]]])
    goal, pose = np.array([[0.0, 8.0]]), np.array([[0.0, 0.0, np.pi / 2]])
    env = environment_state(obstacles, np.ones((1, 1), bool), goal, "nearest", pose=pose)
    chunks = np.zeros((1, 4, 16, 2))
    _policy().replanner.layer.choose(env, chunks)
    np.testing.assert_array_equal(seen["primitives"], safety.escape_primitives(ESCAPE_SPEEDS))
    assert seen["mover_uncertainty"] == 0.0
    assert seen["fallback_all"] is True
    _policy(safety_mover_uncertainty=0.05).replanner.layer.choose(env, chunks)
    assert seen["mover_uncertainty"] == 0.05 and seen["halt_lookahead"] == 0
    # the horizon reaches the scorer as the halt lookahead only where the layer predicts movers
    _policy(safety_horizon=20).replanner.layer.choose(env, chunks)
    assert seen["halt_lookahead"] == 0 and seen["continuation"] is None  # no route hint to pursue
    _policy(safety_horizon=20, **_told(moving_obstacles=True)).replanner.layer.choose(env, chunks)
    assert seen["halt_lookahead"] == 20


def test_a_kept_plan_that_fails_its_check_on_a_newer_view_is_replanned_at_once(monkeypatch):
    """Best-of-4 keeps a straight chunk on an open road. At the next step an obstacle is seen 0.3 m
    ahead of the right leader, across the chunk's rest: best-of-K's recheck replans the episode at
    that step (before the filter sees the action); nothing is safe there, and the widest of every
    candidate scored is kept, here an arc (counted as an escape). Where the road stays open the check
    passes and the chunk runs on. Before a wall 0.6 m ahead nothing is safe (the samples drive on, the
    only manoeuvres here are 0.6 m/s arcs) and the widest, a sample, is kept: it fails the check too,
    so the episode replans at every step."""
    from lerobot_formation.core.safety import layer as safety_layer

    monkeypatch.setattr(safety_layer, "ESCAPE_SPEEDS", (0.6,))
    torch.manual_seed(0)  # no filter: it would replan where it intervenes
    config = nearest_config(num_candidates=4)
    policy = FormationDiffusionPolicy(config).eval()
    forward = policy.normalize_action(torch.tensor([0.4, 0.0]))
    T = policy.replanner.chunk_length
    sampler = lambda batch, num_candidates=1, **_: forward.expand(1, num_candidates, T, 2)  # noqa: E731
    goal, pose = np.array([[0.0, 8.0]]), np.array([[0.0, 0.0, np.pi / 2]])

    def seen(obstacles):
        mask = np.ones((1, len(obstacles)), bool)
        return torch.from_numpy(environment_state(np.array([obstacles]), mask, goal, "nearest", pose=pose))

    far, ahead = seen([[4.0, 4.0, 0.3]]), seen([[0.5, 0.7, 0.3]])
    wall = seen([[x, 0.9, 0.3] for x in np.linspace(-1.5, 1.5, 7)])
    for first, second, replans, none_safe, escapes in (
        (far, far, 1, 0, 0),
        (far, ahead, 2, 1, 1),
        (wall, wall, 2, 2, 0),
    ):
        replanner = Replanner.from_config(policy.config, sampler)
        replanner.start(1)
        replanner.act(first, lambda rows: {})
        assert replanner.stats["replans"] == 1
        replanner.act(second, lambda rows: {})
        assert replanner.stats["replans"] == replans
        assert replanner.stats["rechecks_failed"] == replans - 1
        assert replanner.stats["replans_none_safe"] == none_safe
        assert replanner.stats["escapes"] == escapes


def test_bench_safety_controllers_know_the_level_conditions(tmp_path):
    """Under level 5 the controllers with a safety layer get its delay, rate limits and moving
    obstacles; the standard policy and the checkpoint-as-stored controller do not."""
    from lerobot_formation.bench.controllers import make_controller, safety_settings
    from lerobot_formation.bench.settings import ControllerOptions
    from lerobot_formation.core.episodes.levels import get_level
    from lerobot_formation.core.world.dynamics import FormationParams
    from lerobot_formation.policy.checkpoint import load_policy

    conditions = get_level("level5").conditions
    level5 = KnownWorld(
        moving_obstacles=True,
        action_delay=1,
        max_linear_accel=0.5,
        max_angular_accel=2.0,
        obstacle_noise=0.05,
        pose_noise=0.05,
    )
    assert safety_settings(conditions) == {"safety_world": level5}
    assert safety_settings(get_level("level3").conditions) == {}
    bundle = load_policy(save_nearest_checkpoint(tmp_path))
    options = ControllerOptions(candidates=3, conditions=conditions)
    for name, knows in (
        ("diffusion-safe", True),
        ("diffusion-cbf", True),
        ("diffusion", False),
        ("diffusion-policy", False),
    ):
        cfg = make_controller(name, FormationParams(), options, bundle).config
        assert cfg.safety_world == (level5 if knows else KnownWorld()), name
    plain = make_controller(
        "diffusion-safe", FormationParams(), ControllerOptions(candidates=3), bundle
    ).config
    assert dataclasses.asdict(plain)["safety_world"]["max_linear_accel"] is None
    # a scenes file's own velocities: the obstacles move without moving_obstacles, so it predicts them
    assert safety_settings(None, scenes_move=True) == {"safety_world": KnownWorld(moving_obstacles=True)}
    moving = ControllerOptions(candidates=3, scenes_move=True)
    config = make_controller("diffusion-safe", FormationParams(), moving, bundle).config
    assert config.safety_world.moving_obstacles


def test_bench_guided_controller_guides_and_standard_sampling_is_never_guided(tmp_path):
    """``diffusion-guided`` samples one chunk with the checkpoint's clearance guidance (where it sets
    none, the tuned one) and knows the level's actuator and movers; the eager backend is refused by
    name; ``diffusion`` (standard sampling) runs unguided even from a guided checkpoint."""
    from lerobot_formation.bench.controllers import make_controller
    from lerobot_formation.bench.settings import ControllerOptions
    from lerobot_formation.core.episodes.levels import get_level
    from lerobot_formation.core.world.dynamics import FormationParams
    from lerobot_formation.policy.checkpoint import load_policy
    from lerobot_formation.policy.configuration_formation_diffusion import TUNED_SAMPLING_GUIDANCE

    options = ControllerOptions(candidates=3, conditions=get_level("level5").conditions)
    eager = load_policy(save_nearest_checkpoint(tmp_path / "eager"))
    with pytest.raises(ValueError, match="sampling_guidance > 0 runs in the lean and trace samplers"):
        make_controller("diffusion-guided", FormationParams(), options, eager)
    plain = load_policy(save_nearest_checkpoint(tmp_path / "plain", inference_backend="lean"))
    cfg = make_controller("diffusion-guided", FormationParams(), options, plain).config
    assert cfg.sampling_guidance == TUNED_SAMPLING_GUIDANCE > 0
    guided = load_policy(
        save_nearest_checkpoint(tmp_path / "guided", sampling_guidance=2.0, inference_backend="lean")
    )
    cfg = make_controller("diffusion-guided", FormationParams(), options, guided).config
    assert (cfg.num_candidates, cfg.safety_filter, cfg.sampling_guidance) == (1, "none", 2.0)
    assert (cfg.safety_world.action_delay, cfg.safety_world.moving_obstacles) == (1, True)
    assert make_controller("diffusion", FormationParams(), options, guided).config.sampling_guidance == 0
