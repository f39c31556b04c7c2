"""lerobot_formation: multi-agent formation navigation with a diffusion planner, as a LeRobot plugin.

Importing the package registers the gymnasium id ``gym_formation/FormationNav-v0`` only; it stays
light (no torch, no LeRobot), so the NumPy core (``lerobot_formation.core``) imports without them.

The LeRobot side (the ``formation`` env config, the ``formation_diffusion`` policy and its processor
steps) is registered by ``import lerobot_formation.plugin``, or equivalently ``register()``. LeRobot's
CLIs do it themselves: they import the discovery shim ``lerobot_env_formation`` (plugin_shim/), or
every submodule of this package with ``--policy.discover_packages_path=lerobot_formation``.
"""

from gymnasium.envs.registration import register as _register_gym_id
from gymnasium.envs.registration import registry

ENV_ID = "gym_formation/FormationNav-v0"

if ENV_ID not in registry:
    _register_gym_id(
        id=ENV_ID,
        entry_point="lerobot_formation.env:FormationEnv",
        vector_entry_point="lerobot_formation.vector_env:FormationVectorEnv",
        max_episode_steps=600,
    )


def register() -> None:
    """Register everything LeRobot must know before it parses a config or loads a checkpoint: the env
    config ``formation``, the policy ``formation_diffusion`` and its processor steps (imports torch
    and LeRobot; idempotent). Same as ``import lerobot_formation.plugin``."""
    import lerobot_formation.plugin  # noqa: F401


__all__ = ["ENV_ID", "register"]
