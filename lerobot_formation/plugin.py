"""Everything LeRobot must see registered before it parses a config or loads a checkpoint.

Imported by the discovery shim ``lerobot_env_formation`` (plugin_shim/), which LeRobot's CLIs
auto-import. Importing registers the env config ``formation``, the policy config
``formation_diffusion`` (draccus choice registries) and the custom processor step
``formation_egocentric_obstacles`` (LeRobot's ``ProcessorStepRegistry``, needed to load a checkpoint's
preprocessor), and turns on the fast windowed reads of ``lerobot_formation.fast_reads``. The policy
class and its processor factory are found by LeRobot's naming convention
(``configuration_`` -> ``modeling_`` / ``processor_``).

It also shortens one LeRobot warning (``quiet_torchcodec_warning``): on a machine without FFmpeg's
shared libraries, every ``DatasetConfig`` / ``LeRobotDataset`` LeRobot makes tries ``import
torchcodec`` and logs the whole ~35-line loading traceback, twice per ``lerobot-train`` run. This
project's datasets have no videos, so the decoder never matters; the warning becomes one line.
And it makes ``lerobot-eval``'s videos of formation envs end on the frame with the outcome
(``lerobot_compat.keep_final_eval_frame``).

Start-up checks it installs: an uncaught exception caused by a ``ConfigError`` (a bad config value, a
refused checkpoint or output folder) is printed as one line ``error: <message>`` instead of draccus's
parser traceback (``one_line_config_errors``), and the ``error:`` line LeRobot's parser prints for a
draccus ``DecodingError`` says that message (``lerobot_compat.config_errors_in_draccus_messages``);
``lerobot-train`` locks its ``--output_dir``
(``train_lock``, ``lerobot_compat.install_train_output_lock``).
"""

import logging
import sys

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


def one_line_config_errors() -> None:
    """Install a ``sys.excepthook`` (idempotent) that prints an uncaught exception whose chain holds a
    ``ConfigError`` as one line ``error: <message>`` (exit status 1, as for any uncaught exception);
    every other exception goes to the previous hook unchanged. draccus wraps the error of a config
    value in "Couldn't instantiate class ..." and LeRobot's CLIs let that escape with the parser's
    ~70-line traceback."""
    from lerobot_formation.errors import config_error_in_chain

    previous = sys.excepthook
    if getattr(previous, "_formation_one_line", False):
        return

    def hook(exc_type, exc, tb):
        error = config_error_in_chain(exc)
        if error is None:
            previous(exc_type, exc, tb)
        else:
            print(f"error: {error}", file=sys.stderr)

    hook._formation_one_line = True  # type: ignore[attr-defined]
    sys.excepthook = hook


one_line_config_errors()

import lerobot_formation.configuration_formation_diffusion  # noqa: E402, F401
import lerobot_formation.env_config  # noqa: E402, F401
import lerobot_formation.fast_reads  # noqa: E402, F401  (fast windowed reads for low-dim datasets)
import lerobot_formation.processor_formation_diffusion  # noqa: E402, F401  (registers the processor step)
from lerobot_formation.lerobot_compat import (  # noqa: E402
    config_errors_in_draccus_messages,
    install_train_output_lock,
    keep_final_eval_frame,
)

config_errors_in_draccus_messages()  # lerobot-train's "error: `policy`: ..." line gives the reason
install_train_output_lock()  # one lerobot-train run per --output_dir
keep_final_eval_frame()  # lerobot-eval's videos end on the frame with the outcome (render.EpisodeOverlay)
