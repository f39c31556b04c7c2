"""Auto-discovered by LeRobot (distribution name prefix ``lerobot_env_``): registers lerobot_formation.

Importing registers the gym id ``gym_formation/FormationNav-v0`` (package ``__init__``), the env
config ``formation`` and the policy config ``formation_diffusion`` (draccus choice registries). The
policy class and its processors are then found by LeRobot's naming convention
(``configuration_`` -> ``modeling_`` / ``processor_``). No custom processor steps need registering.
It also turns on the fast windowed reads of ``lerobot_formation.fast_reads``.
"""

import lerobot_formation.configuration_formation_diffusion  # noqa: F401
import lerobot_formation.env_config  # noqa: F401
import lerobot_formation.fast_reads  # noqa: F401  (fast windowed reads for low-dim datasets)
