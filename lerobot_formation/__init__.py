"""lerobot_formation: multi-agent formation navigation with a diffusion planner, as a LeRobot plugin.

Importing the package registers the gymnasium id ``gym_formation/FormationNav-v0`` (and, once the
LeRobot glue is installed, the ``formation`` env config and the ``formation_diffusion`` policy).
"""

from gymnasium.envs.registration import register, registry

ENV_ID = "gym_formation/FormationNav-v0"

if ENV_ID not in registry:
    register(
        id=ENV_ID,
        entry_point="lerobot_formation.envs.env:FormationEnv",
        vector_entry_point="lerobot_formation.envs.vector_env:FormationVectorEnv",
        max_episode_steps=600,
    )

__all__ = ["ENV_ID"]
