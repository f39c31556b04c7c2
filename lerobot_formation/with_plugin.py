"""Runs one of LeRobot's console scripts with this plugin imported first.

``python -m lerobot_formation.with_plugin lerobot-edit-dataset ARGS...`` is ``lerobot-edit-dataset
ARGS...`` with the plugin loaded. LeRobot's dataset tools (``lerobot-edit-dataset``,
``lerobot-dataset-viz``) load no third-party plugin (only the CLIs whose ``main()`` calls
``lerobot.utils.import_utils.register_third_party_plugins()`` do: train, eval, record, replay, rollout,
teleoperate, calibrate, setup-motors), so on a machine without FFmpeg they print torchcodec's whole
loading traceback for every dataset they open. With the plugin loaded that is one line
(``plugin.TORCHCODEC_NOTE``). Nothing else changes: the tool parses its own arguments.
"""

from __future__ import annotations

import sys
from importlib.metadata import entry_points


def lerobot_console_scripts() -> dict[str, str]:
    """LeRobot's console scripts: name -> entry point (``module:function``)."""
    return {
        e.name: e.value
        for e in entry_points(group="console_scripts")
        if e.name.startswith("lerobot-") and e.value.startswith("lerobot.")
    }


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    scripts = lerobot_console_scripts()
    if not argv or argv[0] not in scripts:
        given = f"got {argv[0]!r}" if argv else "got none"
        print(
            "usage: python -m lerobot_formation.with_plugin LEROBOT_SCRIPT [ARGS...]; LEROBOT_SCRIPT must "
            f"be one of LeRobot's console scripts ({', '.join(sorted(scripts))}), {given}",
            file=sys.stderr,
        )
        return 2
    import lerobot_env_formation  # noqa: F401  (the discovery module: imports the plugin, as LeRobot's CLIs do)

    (script,) = [e for e in entry_points(group="console_scripts") if e.name == argv[0]]
    sys.argv = argv
    result = script.load()()
    return result if isinstance(result, int) else 0


if __name__ == "__main__":
    raise SystemExit(main())
