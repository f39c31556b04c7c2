"""The lattice search's proposals (``core.safety.lattice_search``): they head for the goal, keep clear of
obstacles where they are predicted, offer different ways, and one episode's never depend on its batch."""

import numpy as np
import pytest

from lerobot_formation.core.controllers.footprint import TeamBody, step_clearances
from lerobot_formation.core.safety.filters import FootprintCheck
from lerobot_formation.core.safety.lattice_search import best_per_key, search_proposals
from lerobot_formation.core.safety.layer import safety_geometry
from lerobot_formation.core.world.scenes import FAR

T = 15  # the shipped chunk's length


def _check(obstacles, velocity=None, uncertainty=0.0) -> FootprintCheck:
    template, dt, radius = safety_geometry()
    obstacles = np.asarray(obstacles, dtype=np.float64)
    return FootprintCheck(
        obstacles,
        TeamBody(template, radius, dt),
        None if velocity is None else np.asarray(velocity, dtype=np.float64),
        mover_uncertainty=uncertainty,
    )


def _clearance(check: FootprintCheck, commands: np.ndarray) -> np.ndarray:
    """(B, W, steps) the footprint's clearance along proposals (B, W, steps, 2), from the body pose."""
    pose, steps = check._origin()
    clear, _ = step_clearances(
        pose, commands, check.obstacles, check.body, check.obstacle_velocity, steps, check.mover_uncertainty
    )
    return clear


def test_in_the_open_the_best_way_drives_at_the_goal():
    check = _check([[[FAR, FAR, 0.0]]])
    found = search_proposals(check, np.array([[0.0, 5.0]]), 0.05, T, ways=3)
    assert found.shape == (1, 3, T, 2)
    np.testing.assert_allclose(found[0, 0], np.tile([0.6, 0.0], (T, 1)))  # straight, full speed


def test_a_wall_ahead_is_gone_round_and_every_way_keeps_the_margin():
    wall = [[x, 1.2, 0.3] for x in np.linspace(-1.2, 0.6, 4)]  # ahead, open on the right
    check = _check([wall])
    found = search_proposals(check, np.array([[0.0, 5.0]]), 0.05, T, ways=3)
    assert (_clearance(check, found) >= 0.05 - 1e-9).all()
    assert (found[0, 0, :, 1] < 0).any()  # it turns right (clockwise), where the wall is open


def test_a_mover_is_avoided_where_it_will_be_not_where_it_is():
    # a mover on the left crossing the team's straight way at 0.8 m/s: where it is now it blocks nothing
    mover = [[[-1.2, 1.0, 0.3]]]
    crossing = [[[0.8, 0.0]]]
    goal = np.array([[0.0, 6.0]])
    moving_check = _check(mover, crossing, uncertainty=0.1)
    still = search_proposals(_check(mover), goal, 0.05, T, ways=1)
    moving = search_proposals(moving_check, goal, 0.05, T, ways=1)
    np.testing.assert_allclose(still[0, 0], np.tile([0.6, 0.0], (T, 1)))  # straight on
    assert _clearance(moving_check, still).min() < 0.0  # where the mover will be: struck
    assert (_clearance(moving_check, moving) >= 0.05 - 1e-9).all()


def test_each_episode_gets_what_it_gets_alone():
    rng = np.random.default_rng(7)
    B, M = 5, 6
    obstacles = np.zeros((B, M, 3))
    obstacles[..., :2] = rng.uniform(-2.5, 2.5, (B, M, 2))
    obstacles[..., 1] += 1.5
    obstacles[..., 2] = rng.uniform(0.2, 0.5, (B, M))
    velocity = rng.normal(0.0, 0.3, (B, M, 2))
    goal = rng.uniform(-4.0, 4.0, (B, 2)) + [0.0, 3.0]
    together = search_proposals(_check(obstacles, velocity, 0.1), goal, 0.05, T, ways=3)
    for b in range(B):
        alone = search_proposals(
            _check(obstacles[b : b + 1], velocity[b : b + 1], 0.1), goal[b : b + 1], 0.05, T, 3
        )
        np.testing.assert_array_equal(together[b], alone[0])
    np.testing.assert_array_equal(
        together, search_proposals(_check(obstacles, velocity, 0.1), goal, 0.05, T, 3)
    )


def test_where_no_primitive_survives_it_proposes_standing():
    # movers closing on the team from all sides at 3 m/s: every primitive is struck within 0.5 s
    ring = np.array(
        [[1.5 * np.cos(a), 1.5 * np.sin(a), 0.2] for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)]
    )
    inward = -3.0 * ring[:, :2] / np.linalg.norm(ring[:, :2], axis=1, keepdims=True)
    found = search_proposals(_check([ring], [inward]), np.array([[0.0, 5.0]]), 0.05, T, ways=2)
    assert found.shape == (1, 2, T, 2) and not found.any()


def test_best_per_key_keeps_the_best_of_each_key_then_the_count_best():
    key = np.array([[1, 1, 2, 3, 3], [0, 0, 0, 0, 0]])
    score = np.array([[0.5, 0.2, 0.9, np.inf, 0.4], [0.3, 0.1, 0.1, 0.2, 0.0]])
    keep = best_per_key(key, score, 2)
    assert keep.tolist() == [[False, True, False, False, True], [False, False, False, False, True]]


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="ways >= 1"):
        search_proposals(_check([[[FAR, FAR, 0.0]]]), np.array([[0.0, 5.0]]), 0.05, T, ways=0)
