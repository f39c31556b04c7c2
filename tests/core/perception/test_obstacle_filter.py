"""The safety layer's obstacle filter: exact observations pass through while the team moves, noisy
ones are smoothed as the gain says (fixed, or a Kalman gain when told the noise), slots that change
order keep their tracks, and the smoothed view stops the ratchet of a noisy barrier."""

import numpy as np
import pytest

from lerobot_formation.core.encodings.encoding import world_to_body
from lerobot_formation.core.perception.obstacle_filter import ObstacleFilter
from lerobot_formation.core.world.dynamics import rollout_poses

DT = 0.1
WORLD = np.array([[1.0, 2.0, 0.3], [-1.5, 3.0, 0.5], [0.5, -2.0, 0.4]])


def _seen(pose):
    """The obstacles in the body frame of a world pose (1, 3)."""
    out = WORLD.copy()
    out[:, :2] = world_to_body(WORLD[None, :, :2], pose)[0]
    return out[None]


def test_exact_observations_of_a_moving_team_pass_through():
    """The tracks are carried along with the executed motion exactly as the team moves, so with
    exact observations the filter's output is the observation itself."""
    filt = ObstacleFilter(1, 3, DT, beta=0.2)
    pose = np.array([[0.0, 0.0, np.pi / 2]])
    mask = np.ones((1, 3), bool)
    for k in range(30):
        motion = np.array([[0.4, 0.8 * np.sin(0.3 * k)]])  # what ran over the last step
        if k:
            pose = rollout_poses(pose, motion[:, None, None], DT)[:, 0, 0]
        out = filt.update(_seen(pose), mask, motion if k else np.zeros((1, 2)))
        np.testing.assert_allclose(out, _seen(pose), atol=1e-9)


def test_noise_of_a_standing_team_shrinks_as_the_gain_says():
    beta, sigma = 0.3, 0.05
    filt = ObstacleFilter(1, 3, DT, beta=beta)
    pose = np.array([[0.0, 0.0, np.pi / 2]])
    rng = np.random.default_rng(0)
    errors = []
    for k in range(3000):
        seen = _seen(pose) + sigma * rng.normal(size=(1, 3, 3))
        out = filt.update(seen, np.ones((1, 3), bool), np.zeros((1, 2)))
        if k > 50:
            errors.append(out[0] - _seen(pose)[0])
    std = np.std(np.array(errors))
    assert std == pytest.approx(sigma * np.sqrt(beta / (2 - beta)), rel=0.1)


def test_reordered_slots_keep_their_tracks_and_new_ones_start_fresh():
    filt = ObstacleFilter(2, 3, DT, beta=0.5)
    pose = np.array([[0.0, 0.0, np.pi / 2]] * 2)
    mask = np.ones((2, 3), bool)
    first = np.concatenate([_seen(pose[:1])] * 2)
    filt.update(first, mask, np.zeros((2, 2)))
    shifted = first.copy()
    shifted[:, :, 0] += 0.1  # every obstacle seen 0.1 m to the right
    swapped = shifted[:, [2, 0, 1]]
    out = filt.update(swapped, mask, np.zeros((2, 2)), rows=np.array([0, 1]))
    np.testing.assert_allclose(out[:, :, 0], first[:, [2, 0, 1], 0] + 0.05)  # halfway: beta = 0.5
    # an observation beyond the gate of every track starts a new one at itself; so does every
    # observation of a reset episode
    filt.reset(rows=[1])
    far = swapped.copy()
    far[0, 0, :2] += 5.0
    out = filt.update(far, mask, np.zeros((2, 2)))
    np.testing.assert_allclose(out[0, 0], far[0, 0])
    assert not np.allclose(out[0, 1:], far[0, 1:])  # the others are still smoothed
    np.testing.assert_allclose(out[1], far[1])
    with pytest.raises(ValueError, match="beta must be in"):
        ObstacleFilter(1, 3, DT, beta=0.0)


def test_an_obstacle_observed_to_move_passes_through():
    filt = ObstacleFilter(1, 3, DT, beta=0.3)
    pose = np.array([[0.0, 0.0, np.pi / 2]])
    mask = np.ones((1, 3), bool)
    filt.update(_seen(pose), mask, np.zeros((1, 2)))
    moved = _seen(pose).copy()
    moved[0, :, 1] += 0.03
    velocity = np.zeros((1, 3, 2))
    velocity[0, 1] = [0.0, 0.3]
    out = filt.update(moved, mask, np.zeros((1, 2)), velocity)
    np.testing.assert_allclose(out[0, 1], moved[0, 1])  # the mover as observed
    np.testing.assert_allclose(out[0, [0, 2], 1], _seen(pose)[0, [0, 2], 1] + 0.3 * 0.03)  # smoothed


def test_smoothing_stops_the_ratchet_of_a_noisy_barrier():
    """A team that cannot back up (v >= 0) presses at an obstacle ahead and observes it with fresh
    Gaussian noise each step (centre and radius, as ``core.perception.conditions`` draws it). On the raw draws
    the CBF filter lets it creep in whenever a draw shows room, and the team ends in contact; on the
    view of the filter told the noise it stays clear over the same draws (margin 0.05 m, level4's
    noise 0.02 m and level5's 0.05 m). At level5's noise the fixed gain 0.3 does not: contact.

    The six runs (two noise levels, three views) are the rows of one batch: each row's dynamics and
    CBF filter are its own, the batch only shares the calls."""
    from lerobot_formation.core.safety.filters import cbf_filter
    from lerobot_formation.core.world import dynamics
    from lerobot_formation.core.world.dynamics import FormationParams
    from lerobot_formation.core.world.geometry import agent_clearances

    params = FormationParams()
    template = np.asarray(params.graph.template)
    low, high = np.array([0.0, -params.omega_max]), np.array([params.v_max, params.omega_max])
    draws = np.random.default_rng(0).normal(size=(400, 3))
    obstacle = np.array([0.5, 1.6, 0.4])
    rows = [(sigma, smooth) for sigma in (0.02, 0.05) for smooth in ("raw", "fixed gain", "told the noise")]
    filters = [
        None
        if smooth == "raw"
        else ObstacleFilter(
            1,
            1,
            params.dt,
            **({"obstacle_noise": sigma, "pose_noise": 0.0} if smooth == "told the noise" else {}),
        )
        for sigma, smooth in rows
    ]
    sigmas = np.array([sigma for sigma, _ in rows])
    B = len(rows)
    state = dynamics.initial_state(np.tile([0.0, 0.0, np.pi / 2], (B, 1)), params)
    executed, gap = np.zeros((B, 2)), np.full(B, np.inf)
    for z in draws:
        seen = obstacle + sigmas[:, None] * z  # (B, 3): each row's draw at its noise
        view = np.concatenate([world_to_body(seen[:, None, :2], state.pose), seen[:, None, 2:]], -1)
        for i, filt in enumerate(filters):
            if filt is not None:
                view[i : i + 1] = filt.update(view[i : i + 1], np.ones((1, 1), bool), executed[i : i + 1])
        executed, _ = cbf_filter(
            np.tile([0.3, 0.0], (B, 1)), view, template, params.agent_radius, 0.05, 2.0, low, high
        )
        state = dynamics.step(state, executed, params)
        pos = dynamics.agent_positions(state)
        gap = np.minimum(gap, agent_clearances(pos, obstacle[None, None], params.agent_radius).min(axis=1))
    closest = dict(zip(rows, gap, strict=True))
    for sigma in (0.02, 0.05):
        assert closest[sigma, "raw"] < 0.0, sigma  # the ratchet: contact at a standstill
        assert closest[sigma, "told the noise"] > 0.0, sigma
    assert closest[0.05, "fixed gain"] < 0.0


def test_told_the_noise_a_standing_teams_estimate_keeps_converging():
    """With the noise stds, the gain is a Kalman gain per track: a standing team's estimate averages
    ever more draws (about 1 / n) down to the gain's floor, far below the fixed gain's 0.42 s."""
    from lerobot_formation.core.perception.obstacle_filter import MIN_GAIN

    sigma = 0.05
    filt = ObstacleFilter(1, 3, DT, obstacle_noise=sigma, pose_noise=0.0)
    pose = np.array([[0.0, 0.0, np.pi / 2]])
    rng = np.random.default_rng(1)
    early, late = [], []
    for k in range(3000):
        seen = _seen(pose) + sigma * rng.normal(size=(1, 3, 3))
        out = filt.update(seen, np.ones((1, 3), bool), np.zeros((1, 2)))
        (early if k < 10 else late if k > 500 else []).append(out[0] - _seen(pose)[0])
    assert np.std(np.array(early)) > 0.3 * sigma  # the first estimates are the first draws, barely averaged
    floor = sigma * np.sqrt(MIN_GAIN / (2 - MIN_GAIN))
    assert np.std(np.array(late)) == pytest.approx(floor, rel=0.2)


def test_told_the_noise_exact_observations_of_a_moving_team_still_pass_through():
    filt = ObstacleFilter(1, 3, DT, obstacle_noise=0.05, pose_noise=0.05)
    pose = np.array([[0.0, 0.0, np.pi / 2]])
    mask = np.ones((1, 3), bool)
    for k in range(30):
        motion = np.array([[0.4, 0.8 * np.sin(0.3 * k)]])
        if k:
            pose = rollout_poses(pose, motion[:, None, None], DT)[:, 0, 0]
        out = filt.update(_seen(pose), mask, motion if k else np.zeros((1, 2)))
        np.testing.assert_allclose(out, _seen(pose), atol=1e-9)
    with pytest.raises(ValueError, match="noise stds must be finite"):
        ObstacleFilter(1, 3, DT, obstacle_noise=-0.1)
