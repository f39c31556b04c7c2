"""The gym env, its vector env, LeRobot env config, render and episode metrics.

Importing this package registers the gymnasium id ``ENV_ID`` (``gym.make(ENV_ID)``); so do ``import
gym_formation`` and ``import lerobot_formation`` (``lerobot_formation.gym_registration``).
"""

from lerobot_formation.gym_registration import ENV_ID, register_env

register_env()

__all__ = ["ENV_ID"]
