import ast
import functools
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")


def _shared_fixture(decorator: ast.expr) -> bool:
    """``@pytest.fixture(scope="module")`` or ``scope="session"``: built once for many tests."""
    return isinstance(decorator, ast.Call) and any(
        k.arg == "scope" and isinstance(k.value, ast.Constant) and k.value.value in ("module", "session")
        for k in decorator.keywords
    )


@functools.cache
def tests_sharing_a_fixture(tests: Path) -> dict[str, frozenset[str]]:
    """Test module (its path as in node ids) -> the names of its tests that use, directly or through
    other fixtures, a module- or session-scoped fixture of that module (a trained checkpoint, a
    generated dataset, a bench run)."""
    out = {}
    for path in sorted(tests.rglob("test_*.py")):
        functions = {
            node.name: ({a.arg for a in node.args.args + node.args.kwonlyargs}, node.decorator_list)
            for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, ast.FunctionDef)
        }
        needs = {name for name, (_, decorators) in functions.items() if any(map(_shared_fixture, decorators))}
        grown = True
        while grown:
            more = {name for name, (args, _) in functions.items() if args & needs} - needs
            needs |= more
            grown = bool(more)
        if users := frozenset(name for name in needs if name.startswith("test")):
            out[path.relative_to(tests.parent).as_posix()] = users
    return out


if importlib.util.find_spec("xdist") is not None:

    def pytest_xdist_make_scheduler(config, log):
        """``--dist loadgroup`` (``scripts/run.sh test`` runs ``-n 2 --dist loadgroup``) with one more
        group: the tests of a module that use a module- or session-scoped fixture of that module
        (``tests_sharing_a_fixture``) go to one worker together, so that fixture is built once, not
        once per worker; every other test is scheduled on its own. (xdist's own groups, ``xdist_group`` marks, reach the scheduler as node-id
        suffixes, which pytest 9.2's node ids no longer carry: pytest-dev/pytest-xdist#1386.)"""
        if config.getvalue("dist") != "loadgroup":
            return None
        from xdist.scheduler import LoadGroupScheduling

        shared = tests_sharing_a_fixture(Path(__file__).resolve().parent)

        class ModuleFixtureScheduling(LoadGroupScheduling):
            def _split_scope(self, nodeid: str) -> str:
                scope = super()._split_scope(nodeid)
                module, *_, name = nodeid.split("::")
                return module if scope == nodeid and name.split("[")[0] in shared.get(module, ()) else scope

        return ModuleFixtureScheduling(config, log)


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
