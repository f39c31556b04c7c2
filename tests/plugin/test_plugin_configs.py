"""configs/*.json parse through draccus into the plugin's config classes; config validation."""

from pathlib import Path

import draccus
import pytest
from lerobot.configs import NormalizationMode
from lerobot.configs.train import TrainPipelineConfig
from lerobot.optim import AdamWConfig, DiffuserSchedulerConfig
from plugin_helpers import tiny_config

from lerobot_formation.envs.env_config import FormationEnvConfig
from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
NAMES = [
    "formation_diffusion_paper",
    "formation_diffusion_cpu",
    "formation_diffusion_tiny",
    "formation_diffusion_hintfree",
    "formation_diffusion_hintfree_paper",
]


def chain(exc: BaseException | None) -> str:
    """The messages of an exception and of its causes."""
    parts = []
    while exc is not None:
        parts.append(str(exc))
        exc = exc.__cause__ or exc.__context__
    return "\n".join(parts)


def parse(name: str, *args: str) -> TrainPipelineConfig:
    with draccus.config_type("json"):
        return draccus.parse(
            TrainPipelineConfig, CONFIGS / f"{name}.json", args=["--dataset.root=/tmp", *args]
        )


@pytest.mark.parametrize("name", NAMES)
def test_config_file_parses(name, tmp_path):
    cfg = parse(name, f"--output_dir={tmp_path / 'out'}")
    assert isinstance(cfg.policy, FormationDiffusionConfig)
    assert isinstance(cfg.env, FormationEnvConfig)
    p = cfg.policy
    assert p.drop_n_last_frames == p.horizon - p.n_action_steps - p.n_obs_steps + 1
    assert p.horizon % 2 ** len(p.down_dims) == 0
    assert p.normalization_mapping["ENV"] is NormalizationMode.IDENTITY
    assert p.use_ema and p.ema_power == 0.75
    assert cfg.dataset.root == "/tmp"
    cfg.validate()  # sets the optimizer and scheduler from the policy presets, as lerobot-train does
    assert isinstance(cfg.optimizer, AdamWConfig)
    assert isinstance(cfg.scheduler, DiffuserSchedulerConfig)


def test_paper_config_holds_the_papers_hyperparameters(tmp_path):
    cfg = parse("formation_diffusion_paper", f"--output_dir={tmp_path / 'out'}")
    p = cfg.policy
    assert tuple(p.down_dims) == (256, 512, 1024)
    assert (p.kernel_size, p.n_groups, p.diffusion_step_embed_dim) == (5, 8, 256)
    assert (p.noise_scheduler_type, p.num_train_timesteps) == ("DDPM", 100)
    assert p.beta_schedule == "squaredcos_cap_v2"
    assert (p.prediction_type, p.clip_sample) == ("epsilon", True)
    assert (p.horizon, p.n_obs_steps, p.n_action_steps, p.drop_n_last_frames) == (64, 2, 10, 53)
    assert cfg.batch_size == 256
    cfg.validate()
    assert cfg.optimizer == AdamWConfig(lr=1.05e-4, betas=(0.95, 0.999), eps=1e-8, weight_decay=1e-6)
    assert (cfg.scheduler.name, cfg.scheduler.num_warmup_steps) == ("cosine", 1000)
    # The class defaults are the paper's too.
    d = FormationDiffusionConfig(device="cpu")
    assert (tuple(d.down_dims), d.diffusion_step_embed_dim) == ((256, 512, 1024), 256)
    assert (d.horizon, d.n_action_steps) == (64, 10)
    assert (d.optimizer_lr, d.scheduler_warmup_steps, d.drop_n_last_frames) == (1.05e-4, 1000, 53)


def test_cli_overrides_the_file(tmp_path):
    cfg = parse(
        "formation_diffusion_tiny",
        "--policy.horizon=32",
        "--policy.drop_n_last_frames=23",
        "--env.obstacle_encoding=grid+list",
    )
    assert cfg.policy.horizon == 32
    assert cfg.env.features["environment_state"].shape == (66,)


def test_drop_n_last_frames_is_derived_or_checked():
    assert tiny_config(horizon=32, n_action_steps=8).drop_n_last_frames == 32 - 8 - 2 + 1
    with pytest.raises(ValueError, match=r"drop_n_last_frames=7 does not match .* = 23"):
        tiny_config(horizon=32, n_action_steps=8, drop_n_last_frames=7)
    with pytest.raises(Exception) as err:  # noqa: B017  (draccus wraps the ValueError, twice)
        parse("formation_diffusion_paper", "--policy.drop_n_last_frames=7")
    message = chain(err.value)
    assert "drop_n_last_frames=7 does not match horizon - n_action_steps - n_obs_steps + 1" in message
    assert "64 - 10 - 2 + 1 = 53" in message


def test_config_errors_stay_visible_through_draccus():
    """draccus says only "Couldn't instantiate class ..."; the ConfigError with the message is in the
    chain, and is what LeRobot's parser prints (tests/test_reliability.py runs the CLIs)."""
    import lerobot_formation.plugin  # noqa: F401  (the DecodingError message, as in the CLIs)
    from lerobot_formation.compat.run_checks import config_error_in_chain

    with pytest.raises(Exception) as err:  # noqa: B017
        parse("formation_diffusion_tiny", "--policy.horizon=30")
    assert str(err.value).startswith("horizon=30 does not fit the U-Net")  # what LeRobot's parser prints
    message = str(config_error_in_chain(err.value))
    assert "horizon=30 does not fit the U-Net" in message and "nearest valid horizons: [28, 32]" in message


def test_n_action_steps_bound():
    with pytest.raises(
        ValueError, match=r"n_action_steps=16 must be in \[1, horizon - n_obs_steps \+ 1\] = \[1, 15\]"
    ):
        tiny_config(n_action_steps=16)


@pytest.mark.parametrize("value", [0.0, -0.5])
def test_bad_ema_power_raises(value):
    with pytest.raises(ValueError, match=f"ema_power must be > 0, got ema_power={value}"):
        tiny_config(ema_power=value)


def test_env_config_validates_encoding():
    with pytest.raises(ValueError, match=r"obstacle_encoding must be one of .* got 'list'"):
        FormationEnvConfig(obstacle_encoding="list")
