"""Blending a new action chunk into the action being executed at a replan, and smoothing it (numpy only).

Why: a chunked policy replans every ``n_action_steps``; the new chunk's first action generally differs
from the last executed one, a step in [v, omega]. The motion jerk (SPEC: the third difference of the
midpoint position over dt^3) sees a step in the velocity twice, so the replan steps dominate it (for the
default model: 1.36 at the two steps after a replan against 0.53 elsewhere, 30 unseen paper scenes).

The rule removes the step over the first m actions of the chunk, keeping the chunk's own shape:

    a'_k = a_k + (1 - (k + 1) / (m + 1)) (a_last - a_0),   k = 0 .. m - 1;   a'_k = a_k,  k >= m

so a'_0 - a_last = (a_0 - a_last) / (m + 1), each of the m + 1 differences from a_last to a'_m carries
1 / (m + 1) of the step plus the chunk's own change, and the rest of the chunk is unchanged. The rule is
affine-equivariant (it commutes with the policy's fixed MIN_MAX action normalisation), so it can be
applied to normalised or to physical actions alike. m = 0 is the identity.

Applied before the safety layer scores the candidates, so best-of-K judges the actions that will be
executed.

``smooth_chunks`` smooths a sampled chunk along time (n passes of the binomial kernel [1, 2, 1] / 4),
entering from the last executed action:

    a'_k = (a_{k-1} + 2 a_k + a_{k+1}) / 4,   a_{-1} = a_last (a_0 without one),   a_T = a_{T-1}

Why: a diffusion sample carries step-to-step noise that the plan does not mean (level3's first 100
tuning scenes: a mean jerk of 0.36 at the steps where a chunk just runs on, half of all jerk). One pass
multiplies a component of frequency w (radians per step) by cos^2(w / 2): 1 for a constant, 0 at the
Nyquist frequency. The second difference the jerk reads multiplies it by 4 sin^2(w / 2), at most 4;
after n passes the product 4 sin^2(w / 2) cos^(2n)(w / 2) is at most 1 (n = 1) or 16/27 (n = 2). The
kernel is symmetric with unit sum, so a constant or a straight ramp is kept away from the chunk's
ends, and a command's bounds are kept (each output is a convex combination of commands).
"""

from __future__ import annotations

import numpy as np


def blend_weights(steps: int, horizon: int) -> np.ndarray:
    """(horizon,) weights 1 - (k + 1) / (m + 1) of the step, for k < m, then 0."""
    if steps < 0:
        raise ValueError(f"blend steps must be >= 0, got {steps}")
    k = np.arange(horizon)
    return np.where(k < steps, 1.0 - (k + 1) / (steps + 1), 0.0)


def blend_replan(chunks, last_action, has_last, steps: int):
    """Blend chunks (B, [K,] T, 2) into the last executed actions (B, 2) where ``has_last`` (B,) is
    true (an episode's first chunk has no predecessor and is left as it is). Works on numpy arrays and
    on torch tensors (the same operations); returns a new array / tensor."""
    if steps == 0:
        return chunks
    last, mask = _last_and_mask(chunks, last_action, has_last)
    w = blend_weights(steps, chunks.shape[-2])
    w = chunks.new_tensor(w)[:, None] if hasattr(chunks, "new_tensor") else w[:, None]
    return chunks + mask * w * (last - chunks[..., :1, :])


def _last_and_mask(chunks, last_action, has_last):
    """The last executed actions (B, 2) and ``has_last`` (B,) shaped to broadcast over chunks (B, [K,]
    T, 2), in the chunks' dtype (numpy or torch alike); checks the shapes."""
    if chunks.shape[-1] != 2 or chunks.ndim not in (3, 4):
        raise ValueError(f"chunks must be (B, T, 2) or (B, K, T, 2), got shape {tuple(chunks.shape)}")
    if tuple(last_action.shape) != (chunks.shape[0], 2):
        raise ValueError(f"last_action must be ({chunks.shape[0]}, 2), got {tuple(last_action.shape)}")
    last = last_action.reshape(chunks.shape[0], *([1] * (chunks.ndim - 2)), 2)
    mask = has_last.reshape((-1,) + (1,) * (chunks.ndim - 1))
    if hasattr(chunks, "new_tensor"):  # torch: the same arithmetic, no import here
        return last.to(chunks.dtype), mask.to(chunks.dtype)
    return last, mask.astype(chunks.dtype)


def smooth_chunks(chunks, last_action, has_last, passes: int):
    """``passes`` passes of the [1, 2, 1] / 4 kernel over chunks (B, [K,] T, 2) along T (module
    docstring), entered from the last executed actions (B, 2) where ``has_last`` (B,) is true (else
    from the chunk's own first action). Numpy arrays or torch tensors; returns a new one. 0: the
    identity."""
    if isinstance(passes, bool) or not (isinstance(passes, int) and passes >= 0):
        raise ValueError(f"smoothing passes must be an integer >= 0, got {passes!r}")
    if passes == 0:
        return chunks
    last, mask = _last_and_mask(chunks, last_action, has_last)
    out = chunks
    for _ in range(passes):
        x, first = out, mask * last + (1 - mask) * out[..., :1, :]
        out = 0.5 * x  # a new array: the neighbours are added in place below
        out[..., 1:, :] += 0.25 * x[..., :-1, :]
        out[..., :-1, :] += 0.25 * x[..., 1:, :]
        out[..., :1, :] += 0.25 * first
        out[..., -1:, :] += 0.25 * x[..., -1:, :]
    return out
