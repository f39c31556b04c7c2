"""scripts/run.sh's torch choice (issue 13): the CPU build from the PyTorch CPU index where there is no
NVIDIA GPU, PyPI's CUDA build when asked for or when that index cannot be reached.

``install_cpu_torch`` is run alone (sourced from run.sh) in a temporary folder whose ``.venv/bin/python``
is this interpreter behind a guard that refuses ``-m pip``, so the fast tests cannot install anything;
the slow one makes a real throw-away venv and installs fake torch/torchvision wheels from a local index.
"""

from __future__ import annotations

import base64
import functools
import hashlib
import http.server
import importlib.util
import subprocess
import sys
import threading
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def _setup_probe():
    """benchmarks/bench_setup_probe.py: its ``run_install`` harness is the one these tests run."""
    path = REPO / "benchmarks" / "bench_setup_probe.py"
    spec = importlib.util.spec_from_file_location("bench_setup_probe", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_probe = _setup_probe()
run_install, CLOSED_PORT_INDEX = _probe.run_install, _probe.CLOSED_PORT_INDEX


def fake_nvidia_smi(tmp_path: Path, works: bool) -> Path:
    bin_dir = tmp_path / "fakebin"
    bin_dir.mkdir(exist_ok=True)
    tool = bin_dir / "nvidia-smi"
    tool.write_text("#!/bin/sh\necho 'GPU 0: Fake'\n" if works else "#!/bin/sh\nexit 9\n")
    tool.chmod(0o755)
    return bin_dir


def test_an_unreachable_cpu_index_costs_one_line(tmp_path):
    """One note and no pip; that it takes seconds (one try, no retries) is
    benchmarks/bench_setup_probe.py's figure, not a timed test."""
    proc, _ = run_install(tmp_path, LEROBOT_FORMATION_TORCH_INDEX=CLOSED_PORT_INDEX)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == [
        f"note: the PyTorch CPU index {CLOSED_PORT_INDEX} is unreachable; "
        "installing the CUDA build of torch from PyPI"
    ]
    assert "pip was called" not in proc.stderr


def test_the_cuda_choice_and_a_working_gpu_skip_the_cpu_index(tmp_path):
    for proc, _ in (
        run_install(
            tmp_path, LEROBOT_FORMATION_TORCH="cuda", LEROBOT_FORMATION_TORCH_INDEX=CLOSED_PORT_INDEX
        ),
        run_install(
            tmp_path,
            path_dirs=(fake_nvidia_smi(tmp_path, works=True),),
            LEROBOT_FORMATION_TORCH_INDEX=CLOSED_PORT_INDEX,
        ),
    ):
        assert proc.returncode == 0 and proc.stdout == "" and proc.stderr == "", proc
    # A failing nvidia-smi (driver missing) counts as no GPU; =cpu asks for the index even so.
    for proc, _ in (
        run_install(
            tmp_path,
            path_dirs=(fake_nvidia_smi(tmp_path, works=False),),
            LEROBOT_FORMATION_TORCH_INDEX=CLOSED_PORT_INDEX,
        ),
        run_install(
            tmp_path,
            path_dirs=(fake_nvidia_smi(tmp_path, works=True),),
            LEROBOT_FORMATION_TORCH="cpu",
            LEROBOT_FORMATION_TORCH_INDEX=CLOSED_PORT_INDEX,
        ),
    ):
        assert proc.returncode == 0 and "is unreachable" in proc.stdout, proc


def test_an_unknown_choice_is_an_error(tmp_path):
    proc, _ = run_install(tmp_path, LEROBOT_FORMATION_TORCH="gpu")
    assert proc.returncode == 2
    assert "LEROBOT_FORMATION_TORCH must be auto, cpu or cuda, got 'gpu'" in proc.stderr


def _wheel(folder: Path, name: str, version: str, requires: tuple[str, ...] = ()) -> str:
    """A minimal pure-Python wheel: just the metadata pip needs to resolve and install it."""
    info = f"{name}-{version}.dist-info"
    files = {
        f"{name}/__init__.py": f"__version__ = {version!r}\n",
        f"{info}/METADATA": f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n"
        + "".join(f"Requires-Dist: {r}\n" for r in requires),
        f"{info}/WHEEL": "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n",
    }
    record = ""
    for path, text in files.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(text.encode()).digest()).rstrip(b"=").decode()
        record += f"{path},sha256={digest},{len(text)}\n"
    files[f"{info}/RECORD"] = record + f"{info}/RECORD,,\n"
    filename = f"{name}-{version}-py3-none-any.whl"
    with zipfile.ZipFile(folder / filename, "w") as z:
        for path, text in files.items():
            z.writestr(path, text)
    return filename


@pytest.mark.slow
def test_the_cpu_build_comes_from_the_index_as_a_matching_pair_in_range(tmp_path):
    index = tmp_path / "index"
    releases = {  # the newest of each is outside the project's range
        "torch": [("2.11.0+cpu", ()), ("2.12.0+cpu", ())],
        "torchvision": [("0.26.0+cpu", ("torch==2.11.0",)), ("0.27.0+cpu", ("torch==2.12.0",))],
    }
    for name, versions in releases.items():
        (index / name).mkdir(parents=True)
        links = "".join(f'<a href="{_wheel(index / name, name, v, r)}">{v}</a>\n' for v, r in versions)
        (index / name / "index.html").write_text(f"<html><body>{links}</body></html>")
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(index))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    work = tmp_path / "work"
    work.mkdir()
    subprocess.run([sys.executable, "-m", "venv", str(work / ".venv")], check=True)
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}"
        proc, _ = run_install(work, guard=False, LEROBOT_FORMATION_TORCH_INDEX=url)
    finally:
        server.shutdown()
    assert proc.returncode == 0, proc
    assert proc.stdout.splitlines() == [
        f"no NVIDIA GPU (or LEROBOT_FORMATION_TORCH=cpu): installing the CPU build of torch from {url}"
    ]
    listed = subprocess.run(
        [
            str(work / ".venv/bin/python"),
            "-c",
            "import torch, torchvision; print(torch.__version__, torchvision.__version__)",
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    assert listed.stdout.split() == ["2.11.0+cpu", "0.26.0+cpu"]
