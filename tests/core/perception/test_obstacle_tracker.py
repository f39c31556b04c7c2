"""The obstacle tracker of the safety layer: velocities from the noisy ``nearest`` observation alone,
and the constant-velocity prediction."""

import numpy as np
import pytest

from lerobot_formation.core.encodings.encoding import encode_nearest
from lerobot_formation.core.encodings.velocity_encoding import body_velocities
from lerobot_formation.core.perception.obstacle_tracker import (
    MOVING_SPEED,
    ObstacleTracker,
    kalman_gains,
    predict_obstacles,
)
from lerobot_formation.core.safety.filters import decode_nearest

SLOTS, DT, NOISE = 12, 0.1, 0.05
OBSTACLES = np.array(
    [
        [
            [1.0, 3.0, 0.4],
            [-1.5, 4.0, 0.5],
            [2.0, 6.0, 0.3],
            [-0.5, 8.0, 0.6],
            [3.0, 1.0, 0.3],
            [-2.5, 1.5, 0.4],
        ]
    ]
)
VELOCITY = np.zeros((1, 6, 2))
VELOCITY[0, 2] = [-0.3, 0.0]  # crossing
VELOCITY[0, 4] = [0.18, 0.24]  # 0.3 m/s diagonally
GOAL = np.array([[0.0, 10.0]])


def _drive(tracker, steps, seed=1, noise=NOISE, rows=None):
    """A team driving and turning among OBSTACLES (two moving), observed with ``noise`` on the pose
    (heading: the same number in rad) and on every obstacle, through the encoding and its decoder.
    Returns per step the estimates and the true body-frame velocities of the observed slots."""
    rng = np.random.default_rng(seed)
    pose = np.array([[0.0, 0.0, np.pi / 2]])
    out = []
    for t in range(steps):
        world = OBSTACLES.copy()
        world[..., :2] += VELOCITY * DT * t
        seen = world + noise * rng.standard_normal(world.shape)
        observed_pose = pose + noise * rng.standard_normal(3)
        env = encode_nearest(seen, np.ones((1, 6), bool), GOAL, observed_pose, SLOTS)
        goal, obstacles, mask = decode_nearest(env, SLOTS)
        estimate = tracker.update(goal, obstacles, mask, rows)
        # the true velocity of each observed slot: the obstacle its centre is nearest to
        a = observed_pose[0, 2] - np.pi / 2
        c, s = np.cos(a), np.sin(a)
        d = world[0, :, :2] - observed_pose[0, :2]
        body = np.stack([d[:, 0] * c + d[:, 1] * s, -d[:, 0] * s + d[:, 1] * c], -1)
        which = np.argmin(np.linalg.norm(obstacles[0, :6, None, :2] - body[None], axis=-1), axis=1)
        truth = body_velocities(VELOCITY, observed_pose)[0, which]
        out.append((estimate[0, :6], truth))
        action = np.array([0.4, 0.4 * np.sin(t / 8)])  # forward, weaving
        pose = pose + DT * np.array(
            [[action[0] * np.cos(pose[0, 2]), action[0] * np.sin(pose[0, 2]), action[1]]]
        )
    return out


def test_tracker_estimates_moving_and_static_obstacles_under_noise():
    """0.05 m noise on every obstacle and on the pose (0.05 rad on the heading, which moves a body-
    frame obstacle 3 m away by 0.15 m): after 3 s each estimate is within 0.1 m/s of the truth, the
    two moving obstacles' at 0.3 m/s and the four static ones' at ~0."""
    tracker = ObstacleTracker(1, SLOTS, DT)
    steps = _drive(tracker, 60)
    errors = np.array([np.linalg.norm(est - truth, axis=-1) for est, truth in steps[30:]])  # (30, 6)
    assert errors.max() < 0.1, errors.max(axis=0)
    assert errors.mean() < 0.04
    est, truth = steps[-1]
    moving = np.linalg.norm(truth, axis=-1) > 0
    assert moving.sum() == 2
    assert np.linalg.norm(est[~moving], axis=-1).max() < 0.1
    assert np.linalg.norm(est[moving], axis=-1) == pytest.approx([0.3, 0.3], abs=0.1)


def test_tracker_without_noise_converges_to_the_exact_velocities():
    """Without noise the estimates become exact (float32 observations aside), moving obstacles
    included: the error a moving obstacle's first steps put into the heading estimate (every
    velocity turning about the goal, which the rotation fit cannot see) is anchored away."""
    tracker = ObstacleTracker(1, SLOTS, DT, prior_speed=100.0)  # almost no shrinkage toward rest
    steps = _drive(tracker, 30, noise=0.0)
    for est, truth in steps[20:]:
        np.testing.assert_allclose(est, truth, atol=1e-3)


def test_tracker_restarts_per_episode():
    """``reset(rows)`` forgets those episodes' tracks: their next estimate is 0 (a new track), the
    other episodes keep theirs."""
    tracker = ObstacleTracker(2, SLOTS, DT)
    for row in (0, 1):
        _drive(tracker, 20, seed=row, rows=np.array([row]))
    assert np.abs(tracker.velocity[:, :6]).max() > 0.2
    tracker.reset(np.array([1]))
    assert (tracker.velocity[1] == 0).all() and not tracker.started[1] and tracker.started[0]
    kept = tracker.velocity[0].copy()
    first = _drive(tracker, 1, rows=np.array([1]))[0][0]
    assert (first == 0).all()
    np.testing.assert_array_equal(tracker.velocity[0], kept)  # another episode's update leaves row 0


def test_kalman_gains_are_the_growing_memory_line_fit_without_a_prior():
    """With no prior on the velocity and no process noise, the n-th measurement's gains are those of
    the least-squares line through all n: K0 = 2(2n - 1) / (n(n + 1)), K1 = 6 / (n(n + 1) dt)."""
    gains = kalman_gains(DT, 0.05, 1e3, 0.0, steps=30)
    n = np.arange(2, 31)
    np.testing.assert_allclose(gains[1:30, 0], 2 * (2 * n - 1) / (n * (n + 1)), rtol=1e-4)
    np.testing.assert_allclose(gains[1:30, 1], 6 / (n * (n + 1) * DT), rtol=1e-4)
    np.testing.assert_array_equal(gains[0], [1.0, 0.0])


def test_predict_obstacles_moves_centres_not_radii():
    obstacles = np.array([[[1.0, 2.0, 0.3], [5.0, 5.0, 0.5]]])
    velocity = np.array([[[0.5, -1.0], [0.0, 0.0]]])
    moved = predict_obstacles(obstacles, velocity, np.array([0.0, 0.2, 1.0]))
    assert moved.shape == (1, 3, 2, 3)
    np.testing.assert_allclose(moved[0, 2, 0], [1.5, 1.0, 0.3])
    np.testing.assert_array_equal(moved[0, :, 1], np.repeat(obstacles[0, 1:], 3, axis=0))


def test_prediction_uncertainty_grows_a_movers_radius_with_time_and_speed():
    """r + u t min(1, |v| / MOVING_SPEED): a static obstacle keeps its radius, a slow one grows in
    proportion to its speed, a mover at MOVING_SPEED or faster by u t."""
    obstacles = np.array([[[1.0, 2.0, 0.3], [5.0, 5.0, 0.5], [0.0, 3.0, 0.4]]])
    velocity = np.array([[[0.3, 0.4], [0.0, 0.0], [0.5 * MOVING_SPEED, 0.0]]])
    times = np.array([0.0, 0.5, 2.0])
    grown = predict_obstacles(obstacles, velocity, times, uncertainty=0.1)
    np.testing.assert_allclose(grown[0, :, 0, 2], 0.3 + 0.1 * times)
    np.testing.assert_array_equal(grown[0, :, 1, 2], 0.5)
    np.testing.assert_allclose(grown[0, :, 2, 2], 0.4 + 0.05 * times)
    exact = predict_obstacles(obstacles, velocity, times)
    np.testing.assert_array_equal(grown[..., :2], exact[..., :2])  # centres as without it
    np.testing.assert_array_equal(exact[..., 2], np.broadcast_to(obstacles[:, None, :, 2], exact.shape[:-1]))


def test_tracker_refuses_bad_shapes_and_settings():
    with pytest.raises(ValueError, match="gate must be > 0, got 0"):
        ObstacleTracker(1, SLOTS, DT, gate=0.0)
    tracker = ObstacleTracker(1, SLOTS, DT)
    with pytest.raises(ValueError, match=r"obstacles \(b, 12, 3\)"):
        tracker.update(np.zeros((1, 2)), np.zeros((1, 5, 3)), np.zeros((1, 5), bool))
