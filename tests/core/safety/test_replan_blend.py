"""core.safety.replan_blend: the step a replan makes in [v, omega] is spread over the chunk's first m actions."""

import numpy as np
import pytest
import torch

from lerobot_formation.core.safety.replan_blend import blend_replan, blend_weights, smooth_chunks


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


def _smoothed_by_convolution(chunks, last, has_last, passes):
    """The definition: pad with the last executed action (or the first) and the last, convolve."""
    out = chunks.copy()
    for _ in range(passes):
        first = np.where(has_last[:, None, None, None], last[:, None, None, :], out[..., :1, :])
        padded = np.concatenate([first, out, out[..., -1:, :]], axis=-2)
        out = np.apply_along_axis(lambda x: np.convolve(x, [0.25, 0.5, 0.25], "valid"), -2, padded)
    return out


@pytest.mark.parametrize("passes", [1, 2, 3])
def test_smoothing_is_the_binomial_convolution_entered_from_the_last_action(passes):
    c = _chunks((4, 3, 15, 2))
    last = _chunks((4, 2), seed=1)
    has = np.array([True, False, True, False])
    out = smooth_chunks(c, last, has, passes)
    np.testing.assert_allclose(out, _smoothed_by_convolution(c, last, has, passes), atol=1e-12)
    np.testing.assert_allclose(smooth_chunks(c[:, 0], last, has, passes), out[:, 0], atol=1e-12)
    as_torch = smooth_chunks(torch.from_numpy(c), torch.from_numpy(last), torch.from_numpy(has), passes)
    np.testing.assert_allclose(as_torch.numpy(), out, atol=1e-12)
    assert smooth_chunks(c, last, has, 0) is c


def test_smoothing_keeps_constants_ramps_and_bounds_and_damps_the_jerk():
    ramp = np.zeros((1, 20, 2))
    ramp[0, :, 0] = np.linspace(0.0, 0.38, 20)
    kept = smooth_chunks(ramp, np.array([[-0.02, 0.0]]), np.ones(1, bool), 2)  # entered from the ramp's past
    np.testing.assert_allclose(kept[0, :-2], ramp[0, :-2], atol=1e-12)  # a ramp, away from the end
    still = smooth_chunks(np.full((1, 20, 2), 0.3), np.full((1, 2), 0.3), np.ones(1, bool), 3)
    np.testing.assert_allclose(still, 0.3)
    noisy = _chunks((200, 30, 2), seed=2)  # in [-1, 1]
    smooth = smooth_chunks(noisy, np.zeros((200, 2)), np.zeros(200, bool), 2)
    assert smooth.min() >= -1 and smooth.max() <= 1
    second_difference = lambda x: np.abs(np.diff(x, n=2, axis=-2)).mean()  # noqa: E731
    assert second_difference(smooth) < 0.2 * second_difference(noisy)


def test_smoothing_checks_its_arguments():
    c = _chunks((2, 15, 2))
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match=f"smoothing passes must be an integer >= 0, got {bad!r}"):
            smooth_chunks(c, np.zeros((2, 2)), np.ones(2, bool), bad)
    with pytest.raises(ValueError, match=r"last_action must be \(2, 2\)"):
        smooth_chunks(c, np.zeros((3, 2)), np.ones(2, bool), 1)
