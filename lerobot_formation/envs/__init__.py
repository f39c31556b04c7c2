"""The gym env, its vector env, LeRobot env config, render and episode metrics.

Importing this package registers the gymnasium id ``ENV_ID`` (``gym.make(ENV_ID)``); so does
``import gym_formation``, the package that names the namespace.
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
