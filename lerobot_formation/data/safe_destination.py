"""The generator's destination folder, written safely: a temporary sibling ``.NAME.tmp-PID``
renamed into place (never over a folder that appeared meanwhile), stale temporaries of killed runs
removed, and SIGTERM / SIGHUP turned into SystemExit so that every cleanup runs.

What ``--overwrite`` may replace (``check_replaceable``): only a folder this project wrote, i.e. a
LeRobot dataset whose ``meta/info.json`` has the formation features (``FORMATION_FEATURES``) and that
holds nothing but a dataset's entries (``DATASET_ENTRIES``), or an empty folder. Anything else (a
file, a symbolic link, a folder of the user's) is refused with the path and the reason, and nothing
is deleted. Repo ids follow the hub's grammar (``check_repo_id``) and every destination built from
one must lie inside its root folder (``check_inside``).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sys
from pathlib import Path

# The features every PAC dataset has (dataset_frames.dataset_features): the marker of "ours".
FORMATION_FEATURES = (
    "observation.state",
    "observation.environment_state",
    "action",
    "scene.seed",
    "scene.obstacles",
    "scene.goal",
    "scene.start",
)
# What a LeRobot dataset folder holds (README.md: the hub folder's dataset card).
DATASET_ENTRIES = frozenset({"meta", "data", "videos", "images", "README.md"})
# What huggingface_hub's cache folder of one repository holds.
HUB_CACHE_ENTRIES = frozenset({"blobs", "snapshots", "refs", ".no_exist"})


def check_repo_id(repo_id: str) -> str:
    """``repo_id`` if it is ``owner/name`` in the hub's grammar (``huggingface_hub``'s
    ``validate_repo_id``: letters, digits, '-', '_' and '.', no '..' or '--', no leading or trailing
    '-' or '.', at most 96 characters); ValueError naming the value otherwise. So no repo id is an
    absolute path or climbs out of the folder it is joined to."""
    from huggingface_hub.utils import HFValidationError, validate_repo_id

    if not isinstance(repo_id, str) or repo_id.count("/") != 1:
        raise ValueError(f"--repo-id must look like 'owner/name', got {repo_id!r}")
    try:
        validate_repo_id(repo_id)
    except HFValidationError as e:
        raise ValueError(
            f"--repo-id must look like 'owner/name' in the hub's grammar (letters, digits, '-', '_', '.'; "
            f"no '..' or '--'; not starting or ending with '-' or '.'), got {repo_id!r}"
        ) from e
    return repo_id


def check_inside(path: Path, root: Path, what: str) -> Path:
    """``path`` if it lies inside ``root`` once both are resolved (symbolic links, '..'); ValueError
    naming both otherwise."""
    resolved, base = Path(path).resolve(), Path(root).resolve()
    if resolved == base or base not in resolved.parents:
        raise ValueError(f"{what} {path} lies outside its root folder {root}; nothing was written")
    return Path(path)


def _formation_dataset_reason(folder: Path) -> str | None:
    """None if ``folder/meta/info.json`` describes a formation dataset, else why not."""
    info = folder / "meta" / "info.json"
    try:
        features = json.loads(info.read_text())["features"]
    except FileNotFoundError:
        return "it has no meta/info.json"
    except (OSError, ValueError, KeyError, TypeError):
        return "its meta/info.json is not a LeRobot dataset's"
    if not isinstance(features, dict) or not all(k in features for k in FORMATION_FEATURES):
        return "its meta/info.json lacks the formation features (scene.seed, scene.obstacles, ...)"
    return None


def check_replaceable(folder: Path, hub_cache: bool = False) -> None:
    """Raise FileExistsError (path and reason) unless ``--overwrite`` may replace ``folder``: it does
    not exist, is empty, or is a formation dataset this project wrote holding only a dataset's
    entries. ``hub_cache``: ``folder`` is a hub cache folder (``blobs/``, ``snapshots/``, ``refs/``)
    whose every snapshot is such a dataset."""
    folder = Path(folder)
    if not os.path.lexists(folder):
        return
    refuse = (
        f"--overwrite replaces only a formation dataset this project wrote; {folder} is not one "
        "({reason}): nothing was deleted. Choose another folder, or remove it yourself"
    )
    if folder.is_symlink() or not folder.is_dir():
        kind = "a symbolic link" if folder.is_symlink() else "a file"
        raise FileExistsError(refuse.format(reason=f"it is {kind}"))
    entries = sorted(p.name for p in folder.iterdir())
    if not entries:
        return
    allowed = HUB_CACHE_ENTRIES if hub_cache else DATASET_ENTRIES
    foreign = [e for e in entries if e not in allowed]
    if foreign:
        shown = ", ".join(foreign[:5]) + (", ..." if len(foreign) > 5 else "")
        raise FileExistsError(refuse.format(reason=f"it holds {shown}, which a dataset does not"))
    if hub_cache:
        snapshots = sorted((folder / "snapshots").glob("*")) if (folder / "snapshots").is_dir() else []
        reasons = [_formation_dataset_reason(s) for s in snapshots] or ["it has no snapshot"]
        reason = next((r for r in reasons if r is not None), None)
    else:
        reason = _formation_dataset_reason(folder)
    if reason is not None:
        raise FileExistsError(refuse.format(reason=reason))


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
