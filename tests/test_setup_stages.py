"""scripts/run.sh setup talks (issue 27): one ``[setup]`` line per stage with its time and the size of
.venv, and setuptools' warning box filtered out of pip's output.

``setup`` runs sourced from run.sh in a temporary folder whose ``.venv/bin/python`` is a stub: it logs
what it is asked, "installs" by writing files of known size, and refuses the CPU-index probe, so no
package is installed and nothing is downloaded.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
FUNCTIONS = f"source <(sed -e '/^cd /d' -e '/^cmd=/,$d' '{REPO}/scripts/run.sh')\n"

STUB = r"""#!/usr/bin/env bash
# A fake .venv/bin/python: every call is logged; pip installs write files into .venv.
venv="$(cd "$(dirname "$0")/.." && pwd)"
echo "$*" >> "$venv/calls.log"
case "$1" in
  -m)
    case "$*" in
      *"pip install -q torch"*) head -c 3000000 /dev/zero > "$venv/torch.bin"; touch "$venv/has_torch" ;;
      *"pip install -q -e"*)
        head -c 1000000 /dev/zero > "$venv/lerobot.bin"
        printf '%s\n' "/x/setuptools/command/editable_wheel.py:352: InformationOnly: Editable installation." \
          '!!' '' '        ****' '        Please be careful with folders' '        ****' '' '!!' \
          '  with strategy, WheelFile(wheel_path, "w") as wheel_obj:' 'a line pip printed'
        ;;
    esac
    exit 0 ;;
  -) exit 1 ;;  # the CPU-index probe: unreachable
  -I)  # isolated checks: the earlier layout's distribution (only with the marker file), the final import
    case "$3" in
      *'distribution("lerobot_formation")'*) [ -f "$venv/old_layout" ] ;;
      *) exit 0 ;;
    esac ;;
  -c)
    case "$2" in
      'import torch') [ -f "$venv/has_torch" ] ;;
      *torch.version.cuda*) echo "2.11.0 (CUDA build)" ;;
      *'m.version("lerobot")'*) echo "0.6.1" ;;
      *) exit 0 ;;
    esac ;;
esac
"""


def test_setup_prints_one_line_per_stage_with_time_and_size(tmp_path):
    bin_dir = tmp_path / ".venv" / "bin"
    bin_dir.mkdir(parents=True)
    (bin_dir / "python").write_text(STUB)
    (bin_dir / "python").chmod(0o755)
    (tmp_path / "pyproject.toml").write_text("[project]\nname = 'x'\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith("LEROBOT_FORMATION_TORCH")}
    env["LEROBOT_FORMATION_TORCH"] = "cpu"  # ask for the CPU index: the stub's probe refuses it
    env["LEROBOT_FORMATION_TORCH_INDEX"] = "http://127.0.0.1:9/whl/cpu"
    proc = subprocess.run(
        ["bash", "-c", "set -euo pipefail\n" + FUNCTIONS + "setup\n"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc
    lines = proc.stdout.splitlines()
    stages = [line for line in lines if line.startswith("[setup]") and " in " in line]
    assert [s.split(" in ")[0] for s in stages] == [
        "[setup] environment and pip ready",
        "[setup] torch 2.11.0 (CUDA build) installed",
        "[setup] LeRobot 0.6.1 + lerobot_formation installed",
    ]  # one install: the plugin and its discovery module are one distribution
    sizes = [s.rsplit(".venv now ", 1)[1].split() for s in stages]
    megabytes = [float(n) * (1024 if unit == "GB" else 1) for n, unit in sizes]
    assert megabytes[0] + 2 <= megabytes[1] < megabytes[2]  # torch wrote 3 MB, LeRobot 1 MB more
    assert all(s.split(" in ")[1].split(" s,")[0].isdigit() for s in stages)
    # The note about the CPU index, and the box gone from pip's output but pip's own line kept.
    assert any(line.startswith("note: the PyTorch CPU index") for line in lines)
    assert "a line pip printed" in lines and not any(
        "!!" in line or "InformationOnly" in line for line in lines
    )
    assert (tmp_path / ".venv" / ".installed").is_file()
    # Set up already: nothing to do, nothing printed.
    again = subprocess.run(
        ["bash", "-c", "set -euo pipefail\n" + FUNCTIONS + "setup\n"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert again.returncode == 0 and again.stdout == "", again


def test_quiet_pip_keeps_other_warnings_and_lines():
    text = "\n".join(
        [
            "WARNING: Location 'x' is ignored",
            "",
            "/s/dist.py:1: SetuptoolsDeprecationWarning: License classifiers are deprecated.",
            "!!",
            "        ****",
            "!!",
            "  self._finalize_license_expression()",
            "/s/y.py:3: UserWarning: a warning without a box",
            "ERROR: a real error",
        ]
    )
    proc = subprocess.run(
        ["bash", "-c", FUNCTIONS + "quiet_pip"], input=text, capture_output=True, text=True, timeout=30
    )
    assert proc.stdout.splitlines() == [
        "/s/y.py:3: UserWarning: a warning without a box",
        "ERROR: a real error",
    ]


def test_setup_uninstalls_the_earlier_layouts_distribution_first(tmp_path):
    """A .venv set up before the plugin and its discovery module became one distribution
    (lerobot_env_formation) still has lerobot_formation: setup removes it before installing, in one
    line, and the stamp is pyproject.toml's hash alone (as benchmarks/bench_demo_time.py reads it)."""
    venv = tmp_path / ".venv"
    (venv / "bin").mkdir(parents=True)
    (venv / "bin" / "python").write_text(STUB)
    (venv / "bin" / "python").chmod(0o755)
    (venv / "has_torch").touch()
    (venv / "old_layout").touch()
    (tmp_path / "pyproject.toml").write_text("[project]\nname = 'x'\n")
    proc = subprocess.run(
        ["bash", "-c", "set -euo pipefail\n" + FUNCTIONS + "setup\n"],
        cwd=tmp_path,
        env={**os.environ, "LEROBOT_FORMATION_TORCH": "cuda"},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc
    notes = [line for line in proc.stdout.splitlines() if "lerobot_formation uninstalled" in line]
    assert len(notes) == 1 and notes[0].startswith("[setup] "), proc.stdout
    calls = (venv / "calls.log").read_text().splitlines()
    uninstall = calls.index("-m pip uninstall -q -y lerobot_formation")
    install = next(i for i, c in enumerate(calls) if c.startswith("-m pip install -q -e"))
    assert uninstall < install
    want = hashlib.sha256((tmp_path / "pyproject.toml").read_bytes()).hexdigest()[:16]
    assert (venv / ".installed").read_text().strip() == want
