"""The one place that touches LeRobot internals (names that are not LeRobot's public API).

Each use is checked against the LeRobot version it was written for (``TESTED``); on another version
the stock behaviour is used where one exists, or a clear error names what changed.
"""

from __future__ import annotations

import logging

from torch import Tensor

TESTED = ("0.6.",)
logger = logging.getLogger(__name__)


def lerobot_version() -> str:
    import lerobot

    return getattr(lerobot, "__version__", "unknown")


def version_is_tested() -> bool:
    return lerobot_version().startswith(TESTED)


def global_conditioning(model, batch: dict[str, Tensor]) -> Tensor:
    """``DiffusionModel._prepare_global_conditioning``: the FiLM conditioning vector (B, cond) of a
    batch of normalised observation histories (B, n_obs_steps, ...). There is no public method that
    returns it; ``generate_actions`` computes it and samples in one go."""
    fn = getattr(model, "_prepare_global_conditioning", None)
    if fn is None:
        raise RuntimeError(
            f"LeRobot {lerobot_version()}'s DiffusionModel has no _prepare_global_conditioning "
            f"(written for {TESTED}); batched candidate sampling needs an update of lerobot_compat.py"
        )
    return fn(batch)


def caller_policy_config():
    """The ``policy_cfg`` argument of LeRobot's ``make_env_pre_post_processors(env_cfg, policy_cfg)``
    when that function is what called the caller (an ``EnvConfig.get_env_processors``), else None.

    ``lerobot-train`` (after it builds the policy, before the first training step) and ``lerobot-eval``
    (before the first episode) call it, and ``get_env_processors()`` takes no argument: this is the one
    place at start-up where the env config and the policy config meet.
    """
    import sys

    try:
        frame = sys._getframe(2)
    except ValueError:  # called from the top of the stack
        return None
    if frame.f_code.co_name != "make_env_pre_post_processors":
        return None
    return frame.f_locals.get("policy_cfg")


def install_offline_dataset_root_check() -> None:
    """Make ``DatasetConfig`` refuse a ``root`` folder that does not exist while the hub is offline.

    LeRobot looks a missing root up on the hub, which offline (``HF_HUB_OFFLINE=1``) surfaces as a
    ~60-line ``OfflineModeIsEnabled`` traceback from deep inside ``lerobot-train``. LeRobot has no hook
    for a plugin here, so ``DatasetConfig.__post_init__`` is wrapped (idempotent): the original runs
    first, then the check. Online, a missing root is where LeRobot downloads to, and stays allowed.
    """
    from pathlib import Path

    from lerobot.configs.default import DatasetConfig

    original = DatasetConfig.__post_init__
    if getattr(original, "_formation_root_check", False):
        return

    def post_init(self) -> None:
        original(self)
        root = getattr(self, "root", None)
        if root is None or Path(root).exists():
            return
        from huggingface_hub import constants

        if constants.HF_HUB_OFFLINE:
            from lerobot_formation.configuration_formation_diffusion import config_error

            raise config_error(
                f"--dataset.root {root} does not exist, and HF_HUB_OFFLINE is set, so LeRobot cannot download "
                f"it; check the path, or write the dataset there with lerobot-formation-generate --root {root}"
            )

    post_init._formation_root_check = True  # type: ignore[attr-defined]
    DatasetConfig.__post_init__ = post_init
