"""The policy config gives the safety layer and the replanner their settings through one mapping
(``SafetySettings.from_config``, ``PlanSettings.from_config``); the defaults of both are the shipped
default's; the report scripts' overrides go through the same mapping."""

from pathlib import Path

from lerobot.configs.policies import PreTrainedConfig

from lerobot_formation.bench.level_report import safety_overrides
from lerobot_formation.core.safety.layer import CONFIG_FIELDS, SafetySettings
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
    config = FormationDiffusionConfig(safety_margin=0.1, num_candidates=4, sampling_guidance=0.0)
    replanner = Replanner.from_config(config)
    assert replanner.config is config and replanner.settings.num_candidates == 4
    assert replanner.layer.settings == SafetySettings(margin=0.1, guidance=0.0)


def test_the_report_overrides_name_config_fields_through_the_settings():
    overrides = safety_overrides(safety_margin=0.1, layer_ignores_noise=True, halt_lookahead=0)
    assert overrides == {
        "safety_margin": 0.1,
        "safety_obstacle_noise": 0.0,
        "safety_pose_noise": 0.0,
        "safety_halt_lookahead": 0,
    }
    assert SafetySettings(**SafetySettings.from_config_fields(overrides)).margin == 0.1
