"""``--threads N``: one rule for the CPU threads of every command line of the project.

The default is ``$LEROBOT_FORMATION_THREADS``, else ``$OMP_NUM_THREADS``, else 1: the models are tiny
and a machine with few cores is often shared (two processes with two threads each on two cores
crawl), so one thread is the safe choice unless asked otherwise. ``apply_threads(n)`` sets torch's
intra-op threads when torch is already imported, and ``OMP_NUM_THREADS`` / ``MKL_NUM_THREADS`` /
``OPENBLAS_NUM_THREADS`` for what is imported or started later (torch reads them when it first
runs, child processes inherit them). It imports nothing heavy and prints nothing.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Mapping

ENV_VAR = "LEROBOT_FORMATION_THREADS"
THREAD_ENV_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {n}")
    return n


def default_threads(environ: Mapping[str, str] | None = None) -> int:
    """``$LEROBOT_FORMATION_THREADS``, else ``$OMP_NUM_THREADS``, else 1 (unset, empty or not a
    whole number >= 1 falls through to the next)."""
    env = os.environ if environ is None else environ
    for name in (ENV_VAR, "OMP_NUM_THREADS"):
        try:
            n = int(env.get(name, "").strip())
        except ValueError:
            continue
        if n >= 1:
            return n
    return 1


def add_threads_argument(parser: argparse.ArgumentParser, what: str = "CPU threads") -> argparse.Action:
    """Add ``--threads N`` (``args.threads``, an int >= 1) with the default of ``default_threads()``."""
    return parser.add_argument(
        "--threads",
        type=_positive_int,
        default=default_threads(),
        metavar="N",
        help=f"{what} (default: ${ENV_VAR}, else $OMP_NUM_THREADS, else 1; now %(default)s)",
    )


def apply_threads(n: int) -> int:
    """Use ``n`` threads: torch's (only if torch is already imported) and the OpenMP/MKL/OpenBLAS
    variables, for libraries loaded later and for child processes. Returns ``n``."""
    n = int(n)
    if n < 1:
        raise ValueError(f"threads must be >= 1, got {n}")
    for name in THREAD_ENV_VARS:
        os.environ[name] = str(n)
    torch = sys.modules.get("torch")
    if torch is not None and hasattr(torch, "set_num_threads"):
        torch.set_num_threads(n)
    return n
