"""Everything LeRobot must see registered before it parses a config or loads a checkpoint.

Imported by the discovery module ``lerobot_env_formation`` (installed with this package: the
distribution is named for it), which LeRobot's CLIs auto-import. Importing registers the env config
``formation``, the policy config ``formation_diffusion`` (draccus choice registries) and the custom
processor step ``formation_egocentric_obstacles`` (LeRobot's ``ProcessorStepRegistry``, needed to load
a checkpoint's preprocessor), and nothing else: no LeRobot function is replaced and no environment variable is
set. The policy class and its processor factory are found by LeRobot's naming convention
(``configuration_`` -> ``modeling_`` / ``processor_``). The fast dataset reads switch on when a
formation policy's processors are made, for formation datasets only (``compat/fast_reads.py``);
``lerobot-eval``'s videos end on the outcome frame when a formation env is made
(``FormationEnvConfig.create_envs``).

It also shortens one LeRobot warning (``quiet_torchcodec_warning``): on a machine without FFmpeg's
shared libraries, every ``DatasetConfig`` / ``LeRobotDataset`` LeRobot makes tries ``import
torchcodec`` and logs the whole ~35-line loading traceback, twice per ``lerobot-train`` run. This
project's datasets have no videos, so the decoder never matters; the warning becomes one line (a
logging filter; what LeRobot does is unchanged). The start-up checks of a formation run (one-line
config errors, lerobot-train's dataset-root check and output lock, the env config meeting the policy
config) switch on only when one of our configs is built (``compat.run_checks.install_run_hooks``).
"""

import logging

TORCHCODEC_NOTE = (
    "torchcodec cannot be loaded (no FFmpeg 4-8 shared libraries found), so LeRobot decodes videos with "
    "pyav; formation datasets have no videos. Details: python -c 'import torchcodec'. "
    "To use torchcodec: apt-get install ffmpeg."
)


class _TorchcodecLoadWarning(logging.Filter):
    """Replaces LeRobot's "'torchcodec' is installed but cannot be loaded" warning (which embeds the
    full FFmpeg loading traceback) by ``TORCHCODEC_NOTE``, logged once per process."""

    def __init__(self) -> None:
        super().__init__()
        self.shown = False

    def filter(self, record: logging.LogRecord) -> bool:
        if "'torchcodec' is installed but cannot be loaded" not in record.getMessage():
            return True
        if self.shown:
            return False
        self.shown = True
        record.msg, record.args = TORCHCODEC_NOTE, ()
        return True


def quiet_torchcodec_warning() -> None:
    """Install the filter on LeRobot's ``lerobot.utils.import_utils`` logger (idempotent)."""
    logger = logging.getLogger("lerobot.utils.import_utils")
    if not any(isinstance(f, _TorchcodecLoadWarning) for f in logger.filters):
        logger.addFilter(_TorchcodecLoadWarning())


quiet_torchcodec_warning()  # before the imports below, which load LeRobot's configs

import lerobot_formation.envs.env_config  # noqa: E402, F401
import lerobot_formation.policy.configuration_formation_diffusion  # noqa: E402, F401
import lerobot_formation.policy.processor_formation_diffusion  # noqa: E402, F401  (registers the processor step)
