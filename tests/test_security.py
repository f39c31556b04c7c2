"""Issue 26: nothing a user owns is ever deleted, no folder runs code.

- ``--overwrite`` replaces only a dataset this project wrote, never a user's folder (item 1);
- repo ids follow the hub's grammar and every destination stays inside its root (item 2);
- loading a folder never runs code from it: a checkpoint's processor pipelines may name only
  registered processor steps, in our loader (the bench) and in ``lerobot-eval`` (item 3).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import last_error_line, tiny_formation_checkpoint

from datasets_scripts import generate_pac_dataset as gen_mod
from lerobot_formation.data import lerobot_writer
from lerobot_formation.data.hub_folder import push_to_folder


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """A 2-episode formation dataset, as the generator writes it."""
    root = tmp_path_factory.mktemp("ds") / "formation_x"
    lerobot_writer.generate(root, "local/formation_x", 2, workers=0, progress=False)
    return root


def _generate_argv(root: Path, *extra: str) -> list[str]:
    return [
        "--episodes",
        "2",
        "--workers",
        "0",
        "--root",
        str(root),
        "--repo-id",
        "local/x",
        "--no-progress",
        *extra,
    ]


# -- item 1: --overwrite deletes only what this project wrote -----------------------------------------
def test_overwrite_refuses_a_users_folder_and_deletes_nothing(tmp_path, capsys):
    thesis = tmp_path / "thesis"
    (thesis / "docs").mkdir(parents=True)
    (thesis / "docs" / "thesis.txt").write_text("three years of work")
    assert gen_mod.main(_generate_argv(thesis, "--overwrite")) == 2
    line = last_error_line(capsys.readouterr().err)
    assert line.startswith(
        f"error: --overwrite replaces only a formation dataset this project wrote; {thesis}"
    )
    assert "nothing was deleted" in line
    assert (thesis / "docs" / "thesis.txt").read_text() == "three years of work"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["thesis"]  # no temporary folder either


def test_overwrite_refuses_a_dataset_folder_that_holds_a_users_file(dataset, tmp_path, capsys):
    import shutil

    root = tmp_path / "ds"
    shutil.copytree(dataset, root)
    (root / "notes.txt").write_text("mine")
    assert gen_mod.main(_generate_argv(root, "--overwrite")) == 2
    assert "it holds notes.txt, which a dataset does not" in last_error_line(capsys.readouterr().err)
    assert (root / "notes.txt").read_text() == "mine"
    (root / "notes.txt").unlink()  # now it is only the dataset: --overwrite replaces it
    assert gen_mod.main(_generate_argv(root, "--overwrite", "--seed", "7")) == 0
    assert json.loads((root / "meta" / "generation.json").read_text())["seed"] == 7  # replaced
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]  # the old one gone, no temporary left


def test_overwrite_of_the_hub_folder_refuses_a_users_folder(tmp_path, capsys):
    hub = tmp_path / "hub"
    (hub / "local" / "x").mkdir(parents=True)
    (hub / "local" / "x" / "paper.tex").write_text("mine")
    root = tmp_path / "ds"
    assert gen_mod.main(_generate_argv(root, "--overwrite", "--push-to", str(hub))) == 2
    assert f"{hub / 'local' / 'x'} is not one" in last_error_line(capsys.readouterr().err)
    assert (hub / "local" / "x" / "paper.tex").read_text() == "mine"
    assert not root.exists()  # refused before generating


# -- item 2: repo ids in the hub's grammar, destinations inside their root ------------------------------
@pytest.mark.parametrize("repo_id", ["../escaped", "/name", "local/..", "a/b/c", "noslash", "local/x y"])
def test_repo_id_outside_the_hub_grammar_is_refused(repo_id, capsys):
    with pytest.raises(SystemExit) as e:
        gen_mod.parse_args(["--repo-id", repo_id])
    assert e.value.code == 2
    line = last_error_line(capsys.readouterr().err)
    assert "--repo-id must look like 'owner/name'" in line and line.endswith(f"got {repo_id!r}")


def test_hub_folder_never_writes_outside_its_root(dataset, tmp_path):
    hub = tmp_path / "sandbox" / "x" / "y" / "hub"
    summary = json.loads((dataset / "meta" / "generation.json").read_text())
    for repo_id in ("../..", "../x", "/abs"):
        with pytest.raises(ValueError, match="owner/name"):
            push_to_folder(dataset, hub, repo_id, summary, "cmd", overwrite=True)
    assert not (tmp_path / "sandbox").exists()  # nothing written, nothing deleted


def test_default_root_stays_inside_hf_lerobot_home(tmp_path, monkeypatch, capsys):
    from lerobot.utils import constants

    home = tmp_path / "home"
    monkeypatch.setattr(constants, "HF_LEROBOT_HOME", home)
    argv = ["--episodes", "2", "--workers", "0", "--repo-id", "../escaped", "--no-progress"]
    with pytest.raises(SystemExit) as e:
        gen_mod.main(argv)
    assert e.value.code == 2
    assert not (tmp_path / "escaped").exists() and not home.exists()


# -- item 3: loading never runs code from a folder ------------------------------------------------------
def _plant_popen_step(checkpoint: Path, marker: Path) -> None:
    """Make the preprocessor's first step ``subprocess.Popen(["touch", marker])``."""
    f = checkpoint / "policy_preprocessor.json"
    pipeline = json.loads(f.read_text())
    pipeline["steps"].insert(0, {"class": "subprocess.Popen", "config": {"args": ["touch", str(marker)]}})
    f.write_text(json.dumps(pipeline))


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory) -> Path:
    return tiny_formation_checkpoint(tmp_path_factory.mktemp("ckpt") / "pretrained_model")


def test_processor_class_outside_the_registry_is_refused_by_the_loader_and_the_bench(
    tiny_checkpoint, tmp_path, capsys
):
    import shutil

    from lerobot_formation.bench.cli import main as bench_main
    from lerobot_formation.policy.checkpoint import CheckpointError, load_policy

    ckpt = tmp_path / "ckpt"
    shutil.copytree(tiny_checkpoint, ckpt)
    marker = tmp_path / "ran"
    _plant_popen_step(ckpt, marker)
    with pytest.raises(
        CheckpointError, match=r"step 0 names class 'subprocess.Popen', which is not a registered"
    ):
        load_policy(ckpt)
    assert not marker.exists()
    with pytest.raises(SystemExit) as e:
        bench_main(["--controllers", "diffusion", "--policy.path", str(ckpt), "--scenes", "random:1"])
    assert e.value.code == 2
    line = last_error_line(capsys.readouterr().err)
    assert line.startswith(f"error: --policy.path: {ckpt / 'policy_preprocessor.json'} step 0 names class")
    assert "'subprocess.Popen'" in line
    assert not marker.exists()
    # an unknown registry name is refused too (LeRobot would fail on it, but only after the others)
    pipeline = json.loads((ckpt / "policy_preprocessor.json").read_text())
    pipeline["steps"][0] = {"registry_name": "no_such_step", "config": {}}
    (ckpt / "policy_postprocessor.json").write_text(json.dumps(pipeline))
    (ckpt / "policy_preprocessor.json").write_text((tiny_checkpoint / "policy_preprocessor.json").read_text())
    with pytest.raises(CheckpointError, match="registry name 'no_such_step'"):
        load_policy(ckpt)


def test_lerobot_eval_refuses_a_processor_class_before_running_it(tiny_checkpoint, tmp_path):
    import shutil

    ckpt = tmp_path / "ckpt"
    shutil.copytree(tiny_checkpoint, ckpt)
    marker = tmp_path / "ran"
    _plant_popen_step(ckpt, marker)
    env = {
        **os.environ,  # PYTHONPATH too: the subprocess runs the code under test
        "HF_HUB_OFFLINE": "1",
        "HF_LEROBOT_HOME": str(tmp_path / "home"),
        "OMP_NUM_THREADS": "1",
    }
    cmd = [str(Path(sys.executable).parent / "lerobot-eval"), f"--policy.path={ckpt}", "--env.type=formation"]
    cmd += ["--env.obstacle_encoding=grid+list", "--eval.n_episodes=1", "--eval.batch_size=1"]
    cmd += ["--eval.use_async_envs=false", "--policy.device=cpu", f"--output_dir={tmp_path / 'eval'}"]
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode != 0
    assert not marker.exists(), "lerobot-eval ran the planted processor step"
    line = last_error_line(proc.stderr)
    assert line.startswith(
        f"error: {ckpt / 'policy_preprocessor.json'} step 0 names class 'subprocess.Popen'"
    )
