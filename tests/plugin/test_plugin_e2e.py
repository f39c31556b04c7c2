"""End to end through LeRobot's real console scripts, with no plugin flag (the shim distribution).

PAC dataset (datasets_scripts/generate_pac_dataset.py) -> ``lerobot-train`` (tiny config, in-training
env evaluation) -> ``lerobot-eval`` on its checkpoint -> ``lerobot-train --resume=true``.
"""

import importlib.metadata
import json
import sys
from pathlib import Path

import pytest
from safetensors import safe_open

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
TINY = REPO / "configs" / "formation_diffusion_tiny.json"
REPO_ID = "local/formation_plugin_e2e"


def ema_step_and_gap(checkpoint: Path) -> tuple[int, float]:
    """(ema_step, max |EMA - live|) stored in a checkpoint's model.safetensors."""
    with safe_open(checkpoint / "pretrained_model" / "model.safetensors", framework="pt") as f:
        keys = list(f.keys())
        gap = max(
            (f.get_tensor(k) - f.get_tensor(k.removeprefix("ema_"))).abs().max().item()
            for k in keys
            if k.startswith("ema_diffusion.")
        )
        return int(f.get_tensor("ema_step")), gap


def test_shim_distribution_is_installed():
    """LeRobot's CLIs import distributions named lerobot_env_* as the module of that name: the
    project's distribution is lerobot_env_formation (pyproject.toml), its module lerobot_env_formation/."""
    dist = importlib.metadata.distribution("lerobot_env_formation")
    assert dist.metadata["Name"] == "lerobot_env_formation", "run: pip install -e ."


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("e2e")


@pytest.fixture(scope="module")
def dataset_root(workdir) -> Path:
    sys.path.insert(0, str(REPO))
    try:
        from datasets_scripts.generate_pac_dataset import main as generate
    finally:
        sys.path.remove(str(REPO))
    root = workdir / "dataset"
    generate(
        ["--episodes", "3", "--seed", "0", "--repo-id", REPO_ID, "--root", str(root)]
        + ["--obstacle-encoding", "grid+list"]
    )
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["features"]["observation.environment_state"]["shape"] == [66]
    return root


@pytest.fixture(scope="module")
def trained(workdir, dataset_root, run_cli) -> Path:
    out = workdir / "train"
    run_cli(
        "lerobot-train",
        f"--config_path={TINY}",
        f"--dataset.repo_id={REPO_ID}",
        f"--dataset.root={dataset_root}",
        "--env.obstacle_encoding=grid+list",
        "--policy.obstacle_encoding=grid+list",  # stored in the checkpoint, never guessed from the size
        "--policy.egocentric_obstacles=true",  # the CPU config's custom preprocessor step
        f"--output_dir={out}",
        cwd=workdir,
    )
    return out


def test_train_writes_checkpoints_with_ema(trained):
    ckpts = trained / "checkpoints"
    assert sorted(p.name for p in ckpts.iterdir()) == ["000002", "000004", "last"]
    model = ckpts / "last" / "pretrained_model"
    config = json.loads((model / "config.json").read_text())
    assert config["type"] == "formation_diffusion" and config["drop_n_last_frames"] == 7
    step, gap = ema_step_and_gap(ckpts / "last")
    assert step == 4  # one EMA update per optimizer step
    assert gap > 0  # the EMA weights differ from the live ones
    # In-training env evaluation (env_eval_freq=4) rendered its episodes.
    assert len(list((trained / "eval" / "videos_step_000004" / "formation_0").glob("*.mp4"))) == 2
    train_cfg = json.loads((model / "train_config.json").read_text())
    assert train_cfg["optimizer"]["type"] == "adamw"
    steps = json.loads((model / "policy_preprocessor.json").read_text())["steps"]
    names = [s["registry_name"] for s in steps]
    assert names.index("formation_egocentric_obstacles") == names.index("normalizer_processor") - 1


def test_eval_on_checkpoint(trained, workdir, run_cli):
    out = workdir / "eval"
    metrics = out / "formation_metrics.jsonl"
    run_cli(
        "lerobot-eval",
        f"--policy.path={trained / 'checkpoints' / 'last' / 'pretrained_model'}",
        "--env.type=formation",
        "--env.obstacle_encoding=grid+list",
        "--env.episode_length=20",
        f"--env.episode_metrics_path={metrics}",
        "--eval.n_episodes=2",
        "--eval.batch_size=2",
        "--eval.use_async_envs=false",
        "--policy.device=cpu",
        f"--output_dir={out}",
        cwd=workdir,
    )
    info = json.loads((out / "eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == 2
    assert len(info["per_task"][0]["metrics"]["successes"]) == 2
    assert len(list((out / "videos" / "formation_0").glob("*.mp4"))) == 2
    records = [json.loads(line) for line in metrics.read_text().splitlines()]
    assert sorted(r["reset_seed"] for r in records) == [1000, 1001]  # lerobot-eval's default seed
    assert all("final_formation_error" in r and "collision" in r for r in records)


def test_resume_continues_the_run(trained, workdir, run_cli):
    run_cli(
        "lerobot-train",
        f"--config_path={trained / 'checkpoints' / 'last' / 'pretrained_model' / 'train_config.json'}",
        "--resume=true",
        "--steps=6",
        "--env_eval_freq=0",
        cwd=workdir,
    )
    last = trained / "checkpoints" / "last"
    assert last.resolve().name == "000006"
    assert json.loads((last / "training_state" / "training_step.json").read_text())["step"] == 6
    assert ema_step_and_gap(last)[0] == 6  # the EMA step count was restored and continued
