import os
import subprocess
import sys
from pathlib import Path

import pytest

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")


def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist (``scripts/run.sh test`` runs ``-n 2 --dist loadgroup``), the tests that use a
    module- or session-scoped fixture of their own module go to one worker together (an
    ``xdist_group`` named after the module), so that fixture (a trained checkpoint, a generated
    dataset) is built once, not once per worker. Every other test is scheduled on its own."""
    for item in items:
        module = item.nodeid.split("::")[0]
        shared = any(
            fixturedef.scope in ("module", "session") and fixturedef.baseid == module
            for fixturedefs in item._fixtureinfo.name2fixturedefs.values()
            for fixturedef in fixturedefs
        )
        if shared:
            item.add_marker(pytest.mark.xdist_group(name=module))


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Tiny models run fastest on one thread, and a busy 2-core machine makes two threads crawl."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _run_cli(name: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    """A console script of this environment (lerobot-train, lerobot-eval, ...), offline, one thread."""
    env = {
        **os.environ,
        "HF_HUB_OFFLINE": "1",
        "HF_DATASETS_OFFLINE": "1",
        "HF_LEROBOT_HOME": str(cwd / "hf_lerobot_home"),
        "OMP_NUM_THREADS": "1",  # tiny models; two threads on a busy 2-core machine crawl
        "TOKENIZERS_PARALLELISM": "false",
    }
    proc = subprocess.run(
        [str(Path(sys.executable).parent / name), *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    if proc.returncode != 0:
        pytest.fail(f"{name} {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr[-4000:]}")
    return proc


@pytest.fixture(scope="session")
def run_cli():
    """``run_cli(name, *args, cwd=...)``: run a console script; a non-zero exit fails the test."""
    return _run_cli
