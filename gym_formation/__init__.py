"""``gym_formation``: the gymnasium namespace of lerobot_formation's env.

Importing it registers ``gym_formation/FormationNav-v0``, as ``import gym_pusht`` registers
``gym_pusht/PushT-v0``::

    import gymnasium as gym
    import gym_formation  # noqa: F401

    env = gym.make("gym_formation/FormationNav-v0")  # or, without the import above:
    env = gym.make("gym_formation:gym_formation/FormationNav-v0")

``import lerobot_formation`` registers it too (``lerobot_formation.gym_registration``). The env
itself is ``lerobot_formation.envs.env.FormationEnv``.
"""

from lerobot_formation.envs import ENV_ID

__all__ = ["ENV_ID"]
