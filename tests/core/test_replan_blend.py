"""core.replan_blend: the step a replan makes in [v, omega] is spread over the chunk's first m actions."""

import numpy as np
import pytest
import torch

from lerobot_formation.core.replan_blend import blend_replan, blend_weights


def _chunks(shape, seed=0):
    return np.random.default_rng(seed).uniform(-1, 1, shape)


def test_zero_steps_is_the_identity_and_weights_are_a_ramp():
    c = _chunks((3, 15, 2))
    assert blend_replan(c, np.zeros((3, 2)), np.ones(3, bool), 0) is c
    np.testing.assert_allclose(blend_weights(3, 6), [0.75, 0.5, 0.25, 0, 0, 0])
    with pytest.raises(ValueError, match="blend steps must be >= 0, got -1"):
        blend_weights(-1, 6)


@pytest.mark.parametrize("m", [1, 3, 5])
def test_the_step_is_split_in_m_plus_1_equal_parts_and_the_tail_is_unchanged(m):
    c = np.zeros((1, 15, 2))
    c[0, :, 0] = 0.5  # a constant chunk at v = 0.5 after executing v = 0
    out = blend_replan(c, np.array([[0.0, 1.0]]), np.ones(1, bool), m)
    path = np.concatenate([[[0.0, 1.0]], out[0]])  # last executed action, then the new chunk
    steps = np.diff(path[: m + 2], axis=0)
    np.testing.assert_allclose(steps, np.tile(steps[:1], (m + 1, 1)))  # equal steps to a'_m = a_m
    np.testing.assert_allclose(out[0, m:], c[0, m:])
    # the largest change between consecutive actions is 1 / (m + 1) of the raw step
    raw = np.abs(np.diff(np.concatenate([[[0.0, 1.0]], c[0]]), axis=0)).max()
    assert np.abs(np.diff(path, axis=0)).max() == pytest.approx(raw / (m + 1))


def test_candidates_first_chunks_and_torch():
    c = _chunks((4, 3, 15, 2))
    last = _chunks((4, 2), seed=1)
    has = np.array([True, False, True, False])
    out = blend_replan(c, last, has, 3)
    np.testing.assert_array_equal(out[~has], c[~has])  # an episode's first chunk is left alone
    assert not np.allclose(out[has], c[has])
    for b in np.flatnonzero(has):  # each candidate blended into the same executed action
        for k in range(3):
            np.testing.assert_allclose(
                out[b, k], blend_replan(c[b : b + 1, k], last[b : b + 1], has[b : b + 1], 3)[0]
            )
    t = blend_replan(torch.from_numpy(c), torch.from_numpy(last), torch.from_numpy(has), 3)
    np.testing.assert_allclose(t.numpy(), out)


def test_affine_equivariant_so_normalised_and_physical_units_agree():
    low, high = np.array([0.0, -1.5]), np.array([0.6, 1.5])
    norm = _chunks((2, 15, 2))
    last = _chunks((2, 2), seed=2)
    has = np.ones(2, bool)

    def phys(x):
        return (x + 1) / 2 * (high - low) + low

    np.testing.assert_allclose(
        phys(blend_replan(norm, last, has, 4)), blend_replan(phys(norm), phys(last), has, 4)
    )


def test_bad_shapes_are_named():
    with pytest.raises(
        ValueError, match=r"chunks must be \(B, T, 2\) or \(B, K, T, 2\), got shape \(3, 15\)"
    ):
        blend_replan(np.zeros((3, 15)), np.zeros((3, 2)), np.ones(3, bool), 2)
    with pytest.raises(ValueError, match=r"last_action must be \(3, 2\), got \(2, 2\)"):
        blend_replan(np.zeros((3, 15, 2)), np.zeros((2, 2)), np.ones(3, bool), 2)
