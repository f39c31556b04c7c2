"""Blending a new action chunk into the action being executed at a replan (numpy only).

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
    if chunks.shape[-1] != 2 or chunks.ndim not in (3, 4):
        raise ValueError(f"chunks must be (B, T, 2) or (B, K, T, 2), got shape {tuple(chunks.shape)}")
    if tuple(last_action.shape) != (chunks.shape[0], 2):
        raise ValueError(f"last_action must be ({chunks.shape[0]}, 2), got {tuple(last_action.shape)}")
    w = blend_weights(steps, chunks.shape[-2])
    first = chunks[..., :1, :]
    last = last_action[:, None, None, :] if chunks.ndim == 4 else last_action[:, None, :]
    mask = has_last.reshape(-1, *([1] * (chunks.ndim - 1)))
    if hasattr(chunks, "new_tensor"):  # torch
        w = chunks.new_tensor(w)[:, None]
        mask = mask.to(chunks.dtype)
    else:
        w = w[:, None]
        mask = mask.astype(chunks.dtype)
    return chunks + mask * w * (last - first)
