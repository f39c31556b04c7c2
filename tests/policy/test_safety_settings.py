"""The policy config gives the safety layer and the replanner their settings through one mapping
(``SafetySettings.from_config``, ``PlanSettings.from_config``); the defaults of both are the shipped
default's; the report scripts' overrides go through the same mapping; the config keeps five fields
of the safety layer, ``safety_world`` a nested dataclass that save / load and the command line
round-trip."""

from dataclasses import fields
from pathlib import Path

from lerobot.configs.policies import PreTrainedConfig

from lerobot_formation.bench.level_report import safety_overrides
from lerobot_formation.core.safety.layer import CONFIG_FIELDS, KnownWorld, SafetySettings
from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig
from lerobot_formation.policy.replanner import PlanSettings, Replanner

SHIPPED = Path(__file__).resolve().parents[2] / "pretrained" / "formation_diffusion_route_v1"


def test_the_settings_defaults_are_the_config_defaults_and_the_shipped_checkpoints():
    default = FormationDiffusionConfig()
    assert all(hasattr(default, source) for source in CONFIG_FIELDS.values())
    assert SafetySettings.from_config(default) == SafetySettings()
    shipped = PreTrainedConfig.from_pretrained(SHIPPED)
    assert SafetySettings.from_config(shipped) == SafetySettings()
    assert PlanSettings.from_config(shipped) == PlanSettings()


def test_the_replanner_of_a_config_is_told_its_fields():
    world = KnownWorld(action_delay=1)
    config = FormationDiffusionConfig(
        safety_margin=0.1, num_candidates=4, sampling_guidance=0.0, chunk_smoothing=1, safety_world=world
    )
    replanner = Replanner.from_config(config)
    assert replanner.config is config and replanner.settings.num_candidates == 4
    assert replanner.layer.settings == SafetySettings(margin=0.1, world=world)
    # the sampler's settings are the replanner's, with K = 1 too
    assert (replanner.settings.guidance, replanner.settings.chunk_smoothing) == (0.0, 1)


def test_the_report_overrides_name_config_fields_through_the_settings():
    told = KnownWorld(moving_obstacles=True, action_delay=1, obstacle_noise=0.05, pose_noise=0.05)
    overrides = safety_overrides(safety_margin=0.1, layer_ignores_noise=True, horizon=0, world=told)
    assert overrides == {
        "safety_margin": 0.1,
        "safety_horizon": 0,
        "safety_world": KnownWorld(moving_obstacles=True, action_delay=1),
    }
    assert SafetySettings(**SafetySettings.from_config_fields(overrides)).margin == 0.1


def test_the_config_keeps_six_safety_layer_fields():
    layer = [f.name for f in fields(FormationDiffusionConfig) if f.name.startswith("safety_")]
    assert layer == [
        "safety_filter",
        "safety_margin",
        "safety_horizon",
        "safety_mover_uncertainty",
        "safety_world",
        "safety_search",
    ]
    assert sorted(CONFIG_FIELDS.values()) == sorted(layer)


def test_the_known_world_round_trips_through_save_load_and_the_command_line(tmp_path):
    world = KnownWorld(moving_obstacles=True, action_delay=1, max_linear_accel=0.5, pose_noise=0.02)
    config = FormationDiffusionConfig(safety_world=world, safety_horizon=12)
    config.save_pretrained(tmp_path)
    loaded = PreTrainedConfig.from_pretrained(tmp_path)
    assert loaded == config and loaded.safety_world == world
    # the form of --policy.safety_world.action_delay=2 on lerobot-eval / lerobot-train
    cli = ["--safety_world.action_delay=2", "--safety_world.max_angular_accel=2.0"]
    told = PreTrainedConfig.from_pretrained(tmp_path, cli_overrides=cli).safety_world
    assert told == KnownWorld(
        moving_obstacles=True, action_delay=2, max_linear_accel=0.5, max_angular_accel=2.0, pose_noise=0.02
    )
