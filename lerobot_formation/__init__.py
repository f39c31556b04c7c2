"""lerobot_formation: multi-agent formation navigation with a diffusion planner, as a LeRobot plugin.

Subpackages (docs/design.md): ``core`` (numpy), ``compat`` (LeRobot internals), ``envs`` (the gym env,
registered as ``gym_formation/FormationNav-v0`` when ``envs`` is imported), ``policy``
(``formation_diffusion``), ``data`` (the dataset generator), ``bench`` (evaluation). Importing this
package itself imports nothing (no torch, no LeRobot), so the NumPy core imports without them.

The LeRobot side (the ``formation`` env config, the ``formation_diffusion`` policy and its processor
step) is registered by ``import lerobot_formation.plugin``. LeRobot's CLIs do it themselves: they
import the discovery shim ``lerobot_env_formation`` (plugin_shim/), which imports the plugin.
"""
