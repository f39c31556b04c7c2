"""One ``lerobot-train`` run per output folder: a lock file beside it, ``.NAME.train-lock``.

LeRobot refuses an existing ``--output_dir`` only when a run starts and creates the folder at its
first checkpoint, so two runs started into the same new folder (or two resumes of one run) both
train and overwrite each other's checkpoints. With the plugin loaded, ``TrainPipelineConfig.validate``
(the first thing ``lerobot-train`` does) takes an exclusive ``flock`` on ``.NAME.train-lock`` beside
an explicitly given ``--output_dir`` and writes its pid into it; a second run finds the lock held and
refuses with a ``ConfigError`` naming that pid. The lock belongs to the open file, so it ends with
the process however it ends (even SIGKILL): a lock file left by a dead process blocks nothing, the
next run simply takes it over. A run that exits normally removes the file. Only the main process of
a multi-process (``accelerate``) run locks. Where ``fcntl`` is missing (Windows) there is no lock.
"""

from __future__ import annotations

import atexit
import contextlib
import os
from pathlib import Path

from lerobot_formation.errors import ConfigError

try:
    import fcntl
except ImportError:  # not POSIX
    fcntl = None

_held: dict[Path, int] = {}  # output folder -> file descriptor of its lock, held by this process


def lock_path(output_dir: Path) -> Path:
    """The lock file of ``output_dir``: ``.NAME.train-lock`` beside it (not inside: LeRobot refuses
    an existing output folder on a fresh run)."""
    output_dir = Path(output_dir).absolute()
    return output_dir.parent / f".{output_dir.name}.train-lock"


def is_main_process() -> bool:
    """False in the non-main processes of an ``accelerate launch`` (environment variable RANK)."""
    return os.environ.get("RANK", "0") in ("", "0")


def acquire_output_lock(output_dir: Path) -> Path | None:
    """Lock ``output_dir`` for this process (idempotent); returns the lock file, None without fcntl.

    Raises:
        ConfigError: another live process holds the lock (its pid is in the message).
    """
    if fcntl is None:
        return None
    output_dir = Path(output_dir).absolute()
    lock = lock_path(output_dir)
    if output_dir in _held:
        return lock
    lock.parent.mkdir(parents=True, exist_ok=True)
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise ConfigError(
                f"--output_dir {output_dir} is in use by another lerobot-train run (pid {holder}); wait for it "
                f"to finish or choose another --output_dir (lock file {lock})"
            ) from None
        try:  # the holder may have removed the file between our open and our lock: lock the new one
            current = os.path.samestat(os.fstat(fd), os.stat(lock))
        except FileNotFoundError:
            current = False
        if current:
            break
        os.close(fd)
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    _held[output_dir] = fd
    return lock


def release_output_lock(output_dir: Path) -> None:
    """Remove the lock file of ``output_dir`` and unlock it (no-op if this process holds none)."""
    output_dir = Path(output_dir).absolute()
    fd = _held.pop(output_dir, None)
    if fd is None:
        return
    with contextlib.suppress(OSError):
        os.unlink(lock_path(output_dir))  # while still locked, so no one locks the old file meanwhile
    os.close(fd)


@atexit.register
def _release_all() -> None:
    for output_dir in list(_held):
        release_output_lock(output_dir)
