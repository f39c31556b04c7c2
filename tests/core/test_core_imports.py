"""The core stays NumPy only: importing all of it pulls in neither torch, LeRobot nor gymnasium."""

import subprocess
import sys


def test_core_imports_no_torch_or_lerobot():
    code = (
        "import sys, pkgutil, importlib, lerobot_formation.core as c\n"
        "for m in pkgutil.walk_packages(c.__path__, 'lerobot_formation.core.'): importlib.import_module(m.name)\n"
        "bad = [m for m in ('torch', 'lerobot', 'gymnasium') if m in sys.modules]\n"
        "assert not bad, bad\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
