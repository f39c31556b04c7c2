"""Auto-discovered by LeRobot: registers lerobot_formation's env config and policy with LeRobot.

LeRobot's CLIs (``lerobot-train``, ``lerobot-eval``, ...) import every installed distribution whose
name starts with ``lerobot_env_`` (``lerobot.utils.import_utils.register_third_party_plugins``),
by importing the module of the same name. This project's distribution is ``lerobot_env_formation``
(pyproject.toml), so ``pip install -e .`` installs this module beside ``lerobot_formation`` and
``gym_formation``; it imports ``lerobot_formation.plugin`` (the ``formation`` env config, the
``formation_diffusion`` policy and its processor step).
"""

import lerobot_formation.plugin  # noqa: F401
