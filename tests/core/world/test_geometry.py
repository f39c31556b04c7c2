"""``core.world.geometry.xy_clearance``: the clearance every footprint check reads."""

import numpy as np
import pytest

from lerobot_formation.core.world import geometry


def _brute_force(x, y, obstacles, min_axis=None):
    """Every point against every obstacle, with np.hypot: the definition."""
    gaps = []
    for slot in np.moveaxis(obstacles, 1, 0):  # one slot (B, 3) of every scene at a time
        ox, oy, r = slot.T
        distance = np.hypot(x - ox[:, None], y - oy[:, None])
        if min_axis is not None:  # the nearest point of the axis (a footprint's agents)
            distance = distance.min(axis=min_axis)
        gaps.append(distance - r[:, None])
    return np.min(gaps, axis=0)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("shape,min_axis", [((3, 5), None), ((4, 3, 5), 0), ((4, 3, 5), None)])
def test_xy_clearance_takes_all_slots_at_once_or_one_at_a_time_with_the_same_numbers(
    monkeypatch, dtype, shape, min_axis
):
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-3, 3, shape), rng.uniform(-3, 3, shape)
    obstacles = np.concatenate([rng.uniform(-3, 3, (3, 7, 2)), rng.uniform(0.1, 0.5, (3, 7, 1))], axis=-1)
    at_once = geometry.xy_clearance(x, y, obstacles, dtype, min_axis)
    monkeypatch.setattr(geometry, "ALL_SLOTS_AT_ONCE", 0)  # every size takes the slot loop
    one_at_a_time = geometry.xy_clearance(x, y, obstacles, dtype, min_axis)
    assert at_once.dtype == one_at_a_time.dtype == dtype
    assert at_once.shape == one_at_a_time.shape == (shape if min_axis is None else shape[1:])
    assert np.array_equal(at_once, one_at_a_time)
    want = _brute_force(x, y, obstacles, min_axis)
    np.testing.assert_allclose(at_once, want, rtol=0, atol=1e-5 if dtype == np.float32 else 1e-12)


def test_xy_clearance_of_no_obstacle_is_infinite():
    x = np.zeros((4, 2, 3))
    assert np.all(geometry.xy_clearance(x, x, np.zeros((2, 0, 3)), min_axis=0) == np.inf)
    assert geometry.xy_clearance(x, x, np.zeros((2, 0, 3)), min_axis=0).shape == (2, 3)
