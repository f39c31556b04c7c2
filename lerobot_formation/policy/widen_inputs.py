"""A trained policy made to observe a richer obstacle encoding, its behaviour kept: the start of a fine-tune.

LeRobot's diffusion U-Net (``DiffusionConditionalUnet1d``) reads the observation only through the
FiLM layer of each residual block, ``cond_encoder = Sequential(Mish, Linear(cond_dim, ...))``, whose
input is ``[step embedding (E), then per observation step (n_obs_steps): observation.state (S),
observation.environment_state (D)]`` (``DiffusionModel._prepare_global_conditioning``). An encoding
whose feature names contain every name of the old one (``nearest+route`` -> ``nearest+route+velocity``)
keeps each old column's weights, moved to its feature's new position, and gives the new features zero
weights: the widened network computes exactly what the old one did, whatever the new inputs hold,
until training teaches it to use them.
"""

from __future__ import annotations

import numpy as np
import torch

COND_WEIGHT_SUFFIX = "cond_encoder.1.weight"


def column_map(old_names: list[str], new_names: list[str]) -> np.ndarray:
    """For each old feature, the index of the same-named feature in ``new_names``.

    Raises:
        ValueError: an old feature the new encoding does not carry (its name in the message).
    """
    where = {name: i for i, name in enumerate(new_names)}
    missing = [name for name in old_names if name not in where]
    if missing:
        raise ValueError(
            f"the new encoding lacks {len(missing)} feature(s) of the old one, e.g. {missing[:3]}: "
            "a policy can only be widened to an encoding that carries all of its inputs"
        )
    return np.array([where[name] for name in old_names])


def widen_condition_weights(
    weights: dict[str, torch.Tensor],
    old_names: list[str],
    new_names: list[str],
    state_dim: int,
    n_obs_steps: int,
    step_embed_dim: int,
    prefix: str = "",
) -> dict[str, torch.Tensor]:
    """``weights`` (a state dict) with every FiLM ``cond_encoder`` Linear widened from the
    environment features ``old_names`` to ``new_names`` (module docstring); the other tensors are
    returned as they are. Only keys starting with ``prefix`` are widened (e.g. ``"diffusion."``
    to leave an ``ema_diffusion.`` copy alone).

    Raises:
        ValueError: no such layer found, or one whose input width is not the old layout's.
    """
    cols = column_map(old_names, new_names)
    old_d, new_d = len(old_names), len(new_names)
    old_width = step_embed_dim + n_obs_steps * (state_dim + old_d)
    index = [np.arange(step_embed_dim)]
    for k in range(n_obs_steps):
        base = step_embed_dim + k * (state_dim + new_d)
        index += [base + np.arange(state_dim), base + state_dim + cols]
    index = torch.as_tensor(np.concatenate(index))
    out, widened = dict(weights), 0
    for key, w in weights.items():
        if not (key.startswith(prefix) and key.endswith(COND_WEIGHT_SUFFIX)):
            continue
        if w.shape[1] != old_width:
            raise ValueError(
                f"{key} takes {w.shape[1]} inputs, not {old_width} (step embedding {step_embed_dim} + "
                f"{n_obs_steps} x (state {state_dim} + {old_d} environment features))"
            )
        wide = torch.zeros(w.shape[0], step_embed_dim + n_obs_steps * (state_dim + new_d), dtype=w.dtype)
        wide[:, index] = w
        out[key] = wide
        widened += 1
    if not widened:
        raise ValueError(
            f"no '*{COND_WEIGHT_SUFFIX}' tensor under {prefix!r}: not a diffusion U-Net state dict"
        )
    return out
