"""What an unreachable PyTorch CPU index costs scripts/run.sh's setup: its probe (one try, 5 s at
most, no retries) against setup's torch choice with no probe at all, in the same run.

``install_cpu_torch`` is sourced from scripts/run.sh and run alone in a temporary folder whose
``.venv/bin/python`` is this interpreter behind a guard that refuses ``-m pip`` (nothing is
installed), as tests/test_setup_torch.py runs it. The figure: with the index on a closed local port
(refused at once) and no GPU, the probe and its one-line note; the baseline: the same call with
``LEROBOT_FORMATION_TORCH=cuda`` (no probe). This was a wall-clock assertion of the test (under 5 s);
the test keeps the note and that pip is not called. Run: ``python benchmarks/bench_setup_probe.py``
(``--repeats 1`` is a smoke run). The last line is the figure: unreachable index / no probe, with both
times (target: seconds, not pip's retry loop).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CLOSED_PORT_INDEX = "http://127.0.0.1:9/whl/cpu"  # the discard port: nothing listens, refused at once


def run_install(
    folder: Path, guard: bool = True, path_dirs: tuple[Path, ...] = (), **env_vars: str
) -> tuple[subprocess.CompletedProcess, float]:
    """``install_cpu_torch`` alone in ``folder``; its result and wall time. ``guard``: ``.venv/bin/python``
    is this interpreter behind a guard that refuses ``-m pip`` (nothing can be installed); ``path_dirs``
    go first on PATH (e.g. a fake nvidia-smi). Also tests/test_setup_torch.py's harness."""
    venv_bin = folder / ".venv" / "bin"
    if guard:
        venv_bin.mkdir(parents=True, exist_ok=True)
        python = venv_bin / "python"
        python.write_text(
            '#!/bin/sh\ncase "$*" in *"-m pip"*) echo "pip was called" >&2; exit 97;; esac\n'
            f'exec "{sys.executable}" "$@"\n'
        )
        python.chmod(0o755)
    script = f"set -euo pipefail\nsource <(sed -n '/^TORCH_SPECS=/,/^}}/p' '{REPO}/scripts/run.sh')\ninstall_cpu_torch\n"
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PIP_", "LEROBOT_FORMATION_TORCH"))}
    # no real nvidia-smi (the caller says whether there is a GPU), and no pip configuration of the machine
    real = [d for d in env["PATH"].split(os.pathsep) if d and not (Path(d) / "nvidia-smi").exists()]
    env["PATH"] = os.pathsep.join([*map(str, path_dirs), *real])
    env.update(PIP_CONFIG_FILE=os.devnull, PIP_DISABLE_PIP_VERSION_CHECK="1")
    env.update(env_vars)
    t0 = time.perf_counter()
    proc = subprocess.run(
        ["bash", "-c", script], cwd=folder, env=env, capture_output=True, text=True, timeout=300
    )
    return proc, time.perf_counter() - t0


def best_of(folder: Path, repeats: int, **env_vars: str) -> float:
    best = float("inf")
    for _ in range(repeats):
        proc, seconds = run_install(folder, **env_vars)
        if proc.returncode != 0 or "pip was called" in proc.stderr:
            raise SystemExit(f"install_cpu_torch failed ({proc.returncode}): {proc.stdout}{proc.stderr}")
        best = min(best, seconds)
    return best


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    ap.add_argument("--repeats", type=int, default=5, help="timed runs of each case (best; default 5)")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error(f"--repeats must be >= 1, got {args.repeats}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        probe = best_of(folder, args.repeats, LEROBOT_FORMATION_TORCH_INDEX=CLOSED_PORT_INDEX)
        skip = best_of(
            folder,
            args.repeats,
            LEROBOT_FORMATION_TORCH="cuda",
            LEROBOT_FORMATION_TORCH_INDEX=CLOSED_PORT_INDEX,
        )
    print("| setup's torch choice | s |\n|---|---|")
    print(f"| no GPU, CPU index unreachable (probe, note) | {probe:.2f} |")
    print(f"| LEROBOT_FORMATION_TORCH=cuda (no probe) | {skip:.2f} |")
    print(
        f"unreachable index / no probe: {probe / skip:.1f}x ({probe:.2f} s vs {skip:.2f} s; target under 5 s)"
    )


if __name__ == "__main__":
    main()
