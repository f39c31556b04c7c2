"""Everything LeRobot must see registered before it parses a config or loads a checkpoint.

Imported by the discovery shim ``lerobot_env_formation`` (plugin_shim/), which LeRobot's CLIs
auto-import. Importing registers the env config ``formation``, the policy config
``formation_diffusion`` (draccus choice registries) and the custom processor step
``formation_egocentric_obstacles`` (LeRobot's ``ProcessorStepRegistry``, needed to load a checkpoint's
preprocessor), and turns on the fast windowed reads of ``lerobot_formation.fast_reads``. The policy
class and its processor factory are found by LeRobot's naming convention
(``configuration_`` -> ``modeling_`` / ``processor_``).
"""

import lerobot_formation.configuration_formation_diffusion  # noqa: F401
import lerobot_formation.env_config  # noqa: F401
import lerobot_formation.fast_reads  # noqa: F401  (fast windowed reads for low-dim datasets)
import lerobot_formation.processor_formation_diffusion  # noqa: F401  (registers the processor step)
