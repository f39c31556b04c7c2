"""lerobot_formation: multi-agent formation navigation with a diffusion planner, as a LeRobot plugin.

Subpackages (docs/design.md): ``core`` (numpy), ``compat`` (LeRobot internals), ``envs`` (the gym env,
``gym_formation/FormationNav-v0``), ``policy`` (``formation_diffusion``), ``data`` (the dataset
generator), ``bench`` (evaluation). Importing this package itself imports nothing (no gymnasium, no
torch, no LeRobot), so the NumPy core imports without them. It does make gymnasium know the env id:
at once if gymnasium is loaded, else when it loads (``gym_registration``), so ``import
lerobot_formation`` (or ``import gym_formation``) then ``gym.make("gym_formation/FormationNav-v0")``
works.

The LeRobot side (the ``formation`` env config, the ``formation_diffusion`` policy and its processor
step) is registered by ``import lerobot_formation.plugin``. LeRobot's CLIs do it themselves: they
import the discovery module ``lerobot_env_formation`` (installed with this package), which imports the
plugin.
"""

from lerobot_formation.gym_registration import register_when_gymnasium_loads

register_when_gymnasium_loads()
