"""``pip install -e .`` into an existing LeRobot 0.6 environment installs the plugin and its discovery
module in one step (slow tier).

The existing environment is a new venv that sees this environment's packages less this project's own
(a ``.pth`` file naming a folder of links to them), so LeRobot, torch and pip are there without a
download and nothing of this environment is changed. (``python -m venv --system-site-packages`` from a
venv's python gives the base interpreter's site-packages, which has no LeRobot.) The project is
copied first, so the editable install writes its build files into the copy, not the work tree.
"""

from __future__ import annotations

import fnmatch
import shutil
import subprocess
import sys
import sysconfig
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
# this project's entries in a site-packages folder (its distributions, packages, editable finders)
OWN = ("lerobot_env_formation*", "lerobot_formation*", "gym_formation*", "datasets_scripts*", "__editable__*")

DISCOVERY = """
import importlib.metadata as md, sys
assert "lerobot_formation" not in sys.modules
from lerobot.utils.import_utils import register_third_party_plugins
register_third_party_plugins()  # what lerobot-train, lerobot-eval, ... call before parsing
from lerobot.configs.policies import PreTrainedConfig
from lerobot.envs.configs import EnvConfig
assert "formation" in EnvConfig.get_known_choices(), sorted(EnvConfig.get_known_choices())
assert "formation_diffusion" in PreTrainedConfig.get_known_choices()
dist = md.distribution("lerobot_env_formation")
assert str(dist.locate_file("")).startswith(sys.prefix), dist.locate_file("")
assert "LICENSE" in (dist.metadata.get_all("License-File") or []), dist.metadata.get_all("License-File")
print(sys.modules["lerobot_env_formation"].__file__)
"""


def _copy_project(dest: Path) -> None:
    """pyproject.toml, the files it names and the packages its ``packages.find`` includes."""
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())
    include = pyproject["tool"]["setuptools"]["packages"]["find"]["include"]
    dest.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(REPO / name, dest / name)
    tops = {p.name for p in REPO.iterdir() if (p / "__init__.py").is_file()}
    for top in sorted(tops):
        if any(fnmatch.fnmatch(top, pattern) for pattern in include):
            shutil.copytree(REPO / top, dest / top, ignore=shutil.ignore_patterns("__pycache__"))


def _lerobot_environment(venv: Path, tmp_path: Path) -> Path:
    """A venv at ``venv`` that sees this environment's packages without this project's; its python."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    view = tmp_path / "lerobot_env_packages"
    view.mkdir()
    for folder in dict.fromkeys(Path(sysconfig.get_paths()[k]) for k in ("purelib", "platlib")):
        for entry in folder.iterdir():
            if not any(fnmatch.fnmatch(entry.name, p) for p in OWN) and not (view / entry.name).exists():
                (view / entry.name).symlink_to(entry)
    python = venv / "bin" / "python"
    site = subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    (Path(site) / "_existing_lerobot_environment.pth").write_text(f"{view}\n")
    return python


@pytest.mark.slow
def test_pip_install_e_into_an_existing_lerobot_environment(tmp_path):
    src, venv = tmp_path / "project", tmp_path / "venv"
    _copy_project(src)
    python = _lerobot_environment(venv, tmp_path)
    env = {
        "PATH": f"{venv / 'bin'}:/usr/bin:/bin",
        "HOME": str(tmp_path),
        "HF_HUB_OFFLINE": "1",
        "HF_LEROBOT_HOME": str(tmp_path / "hf_lerobot"),
        "OMP_NUM_THREADS": "1",
        "PIP_NO_INDEX": "1",
        "PIP_DISABLE_PIP_VERSION_CHECK": "1",
    }

    def run(*args: str, timeout: int = 300) -> subprocess.CompletedProcess:
        proc = subprocess.run(args, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=timeout)
        assert proc.returncode == 0, f"{args}:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"
        return proc

    # before: LeRobot is there, the plugin is not
    run(
        str(python),
        "-c",
        "import lerobot, torch, importlib.util as u; assert not u.find_spec('gym_formation')",
    )
    run(str(python), "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "-e", str(src))

    proc = run(
        str(python), "-c", "import lerobot_env_formation, gym_formation; print(gym_formation.__file__)"
    )
    assert proc.stdout.strip() == str(src / "gym_formation" / "__init__.py")
    proc = run(str(python), "-c", DISCOVERY)
    assert proc.stdout.strip() == str(src / "lerobot_env_formation" / "__init__.py")
    # the console scripts come with it
    assert (venv / "bin" / "lerobot-formation-bench").is_file()
    run(str(venv / "bin" / "lerobot-formation-bench"), "--help")
