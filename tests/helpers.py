"""Shared builders of the tests in tests/ (pytest puts this folder, which holds conftest.py and no
``__init__.py``, on ``sys.path``): the last line of a CLI's stderr, and tiny untrained diffusion
policies and their checkpoints, and a controller spy."""

from __future__ import annotations

from pathlib import Path

import numpy as np

# The obstacle encoding of a size of observation.environment_state, for the sizes the tests use.
ENCODING_OF_ENV_DIM = {66: "grid+list", 51: "grid", 50: "nearest", 55: "nearest+route"}


def last_error_line(err: str) -> str:
    """The last non-blank line of a CLI's stderr, which must hold no traceback."""
    assert "Traceback" not in err, err
    return [ln for ln in err.strip().splitlines() if ln.strip()][-1]


def tiny_diffusion_kwargs(env_dim: int = 66) -> dict:
    """Config fields of a tiny diffusion policy on the formation features (state 7, environment state
    ``env_dim``, action 2): fields that LeRobot's ``DiffusionConfig`` and ``FormationDiffusionConfig``
    both take."""
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

    return dict(
        device="cpu",
        push_to_hub=False,
        input_features={
            OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(7,)),
            OBS_ENV_STATE: PolicyFeature(type=FeatureType.ENV, shape=(env_dim,)),
        },
        output_features={ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(2,))},
        horizon=16,
        n_action_steps=8,
        down_dims=(16, 32),
        kernel_size=3,
        n_groups=4,
        diffusion_step_embed_dim=16,
    )


def standard_policy_kwargs(env_dim: int = 66) -> dict:
    """``FormationDiffusionConfig`` fields of the standard policy that most tests are written for: the
    encoding of ``env_dim`` (``ENCODING_OF_ENV_DIM``) and every sampling and safety field at the value
    it had before the shipped layer became the default (``compat.run_checks.FIELDS_BEFORE``:
    K = 1, no filter, no guidance, no warm start, no smoothing, the eager backend, the dataset's action
    range, margin 0.1, rate 2, ...)."""
    from lerobot_formation.compat.run_checks import FIELDS_BEFORE

    return {**FIELDS_BEFORE, "obstacle_encoding": ENCODING_OF_ENV_DIM[env_dim]}


def tiny_formation_checkpoint(path: Path, env_dim: int = 66) -> Path:
    """A tiny untrained formation_diffusion policy (``ENCODING_OF_ENV_DIM[env_dim]``, 2 DDIM steps) saved
    in ``path`` with its processors (fixed normalisation stats); returns ``path``."""
    import torch
    from lerobot.utils.constants import ACTION, OBS_STATE

    from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig
    from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy
    from lerobot_formation.policy.processor_formation_diffusion import (
        make_formation_diffusion_pre_post_processors,
    )

    torch.manual_seed(0)
    cfg = FormationDiffusionConfig(
        **tiny_diffusion_kwargs(env_dim),
        **standard_policy_kwargs(env_dim),
        noise_scheduler_type="DDIM",
        num_inference_steps=2,
    )
    stats = {
        OBS_STATE: {"min": torch.full((7,), -5.0), "max": torch.full((7,), 5.0)},
        ACTION: {"min": torch.tensor([0.0, -1.5]), "max": torch.tensor([0.6, 1.5])},
    }
    pre, post = make_formation_diffusion_pre_post_processors(cfg, stats)
    FormationDiffusionPolicy(cfg).save_pretrained(path)
    pre.save_pretrained(path)
    post.save_pretrained(path)
    return path


def stock_diffusion_checkpoint(path: Path) -> Path:
    """A tiny untrained LeRobot ``diffusion`` policy (not ours) on the grid+list features, saved in
    ``path`` without processors; returns ``path``."""
    import torch
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    torch.manual_seed(0)
    DiffusionPolicy(DiffusionConfig(**tiny_diffusion_kwargs())).save_pretrained(path)
    return path


class Spy:
    """Wraps a rollout controller and keeps copies of the views (``Perception``) it was given."""

    def __init__(self, inner):
        self.inner, self.name, self.views = inner, inner.name, []

    def reset(self, view):
        self.views.append(view[np.arange(len(view))])
        self.inner.reset(view)

    def act(self, view, idx):
        self.views.append(view[np.arange(len(view))])
        return self.inner.act(view, idx)


def dataset_file_hashes(root: Path) -> dict[str, str]:
    """sha256 of every file of a generated dataset folder but ``meta/generation.json`` (which holds its
    timing): two generations are the same dataset when these are equal."""
    import hashlib

    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != "generation.json"
    }
