"""Auto-discovered by LeRobot (distribution name prefix ``lerobot_env_``): registers lerobot_formation.

All registration lives in ``lerobot_formation.plugin`` (editable with the main package), so this
one-line module never needs reinstalling when the plugin grows.
"""

import lerobot_formation.plugin  # noqa: F401
