"""The generator's destination folder, written safely: a temporary sibling ``.NAME.tmp-PID``
renamed into place (never over a folder that appeared meanwhile), stale temporaries of killed runs
removed, and SIGTERM / SIGHUP turned into SystemExit so that every cleanup runs."""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
from pathlib import Path


def temporary_path(root: Path) -> Path:
    """Where this process writes ``root`` before the rename: ``.NAME.tmp-PID`` beside it."""
    return root.parent / f"{_tmp_prefix(root)}{os.getpid()}"


def trash_path(root: Path) -> Path:
    """Where this process moves an old ``root`` it replaces (``--overwrite``): ``.NAME.old-PID``."""
    return root.parent / f"{_old_prefix(root)}{os.getpid()}"


def _tmp_prefix(root: Path) -> str:
    return f".{root.name}.tmp-"


def _old_prefix(root: Path) -> str:
    return f".{root.name}.old-"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def remove_stale_temporaries(root: Path) -> list[Path]:
    """Remove the ``.NAME.tmp-PID`` / ``.NAME.old-PID`` folders beside ``root`` that runs killed with
    SIGKILL (no cleanup possible) left behind: those whose PID is no longer alive. Returns them.

    Raises:
        FileExistsError: a live process (not this one) is writing ``root`` now.
    """
    root = Path(root)
    removed = []
    if not root.parent.is_dir():
        return removed
    for prefix in (_tmp_prefix(root), _old_prefix(root)):
        for path in sorted(root.parent.glob(f"{prefix}*")):
            pid_text = path.name[len(prefix) :]
            if not pid_text.isdigit() or int(pid_text) == os.getpid():
                continue
            if _pid_alive(int(pid_text)):
                if prefix == _tmp_prefix(root):
                    raise FileExistsError(
                        f"another generation (pid {pid_text}) is writing {root} now (its temporary folder {path}); "
                        f"wait for it, or remove {path} if process {pid_text} is not a generation"
                    )
                continue
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed


def rename_noreplace(src: Path, dst: Path) -> None:
    """``os.rename(src, dst)`` that never replaces ``dst`` (a folder that appeared meanwhile, even an
    empty one, which plain ``rename`` replaces): ``renameat2(RENAME_NOREPLACE)`` on Linux, atomic;
    elsewhere a check right before the rename. Raises FileExistsError if ``dst`` exists."""
    if sys.platform.startswith("linux"):
        import ctypes
        import errno

        libc = ctypes.CDLL(None, use_errno=True)
        fn = getattr(libc, "renameat2", None)
        if fn is not None:
            AT_FDCWD, RENAME_NOREPLACE = -100, 1
            if fn(AT_FDCWD, os.fsencode(src), AT_FDCWD, os.fsencode(dst), RENAME_NOREPLACE) == 0:
                return
            err = ctypes.get_errno()
            if err == errno.EEXIST:
                raise FileExistsError(
                    f"destination {dst} appeared while this run was generating (another generation?); "
                    "nothing was replaced: pass --overwrite to replace it"
                )
            if err not in (errno.ENOSYS, errno.EINVAL):  # unsupported here: fall back
                raise OSError(err, os.strerror(err), str(src), None, str(dst))
    if os.path.lexists(dst):
        raise FileExistsError(
            f"destination {dst} appeared while this run was generating; nothing was replaced"
        )
    os.rename(src, dst)


@contextlib.contextmanager
def exit_on_signals():
    """SIGTERM (and SIGHUP) raise SystemExit(128 + signal) in the main thread, so every ``finally`` and
    ``except BaseException`` runs: the temporary folder is removed and the workers stopped. (SIGKILL
    cannot be caught: its workers die with it, see ``_die_with_parent``, and the next run removes its
    temporary folder, see ``remove_stale_temporaries``.)"""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise SystemExit(128 + signum)

    names = [n for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n)]
    previous = {n: signal.signal(getattr(signal, n), handler) for n in names}
    try:
        yield
    finally:
        for n, h in previous.items():
            signal.signal(getattr(signal, n), h)
