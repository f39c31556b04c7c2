"""``gym_formation``: the gymnasium namespace of lerobot_formation's env.

Importing it registers ``gym_formation/FormationNav-v0``, as ``import gym_pusht`` registers
``gym_pusht/PushT-v0``::

    import gymnasium as gym
    import gym_formation  # noqa: F401

    env = gym.make("gym_formation/FormationNav-v0")  # or, without the import above:
    env = gym.make("gym_formation:gym_formation/FormationNav-v0")

So does ``import lerobot_formation.envs`` (``import lerobot_formation`` alone imports nothing, so
that the NumPy core loads without gymnasium or torch). The env itself is
``lerobot_formation.envs.env.FormationEnv``.
"""

from lerobot_formation.envs import ENV_ID

__all__ = ["ENV_ID"]
