"""Errors a user can fix: a bad config value or a refused start-up (no torch, no LeRobot here).

``ConfigError`` is a ``ValueError``. draccus wraps a ``ValueError`` raised while it builds a config
in ``ParsingError("Couldn't instantiate class ...")``; with the plugin loaded, LeRobot's CLIs print
an uncaught exception whose chain holds a ``ConfigError`` as one line ``error: <message>``
(``lerobot_formation.plugin.one_line_config_errors``) instead of the parser's traceback.
"""

from __future__ import annotations


class ConfigError(ValueError):
    """A config value, a checkpoint or an output folder that a run refuses; the message names the
    value and what to do."""


def config_error_in_chain(exc: BaseException | None) -> ConfigError | None:
    """The first ``ConfigError`` in ``exc`` and its causes / contexts, or None."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, ConfigError):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None
