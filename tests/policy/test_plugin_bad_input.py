"""Bad input fails at start-up with an error that names the problem."""

import pytest
import torch
from helpers import stock_diffusion_checkpoint
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE
from lerobot.utils.feature_utils import dataset_to_policy_features
from plugin_helpers import formation_features, tiny_config

from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy


def dataset_features(state=(7,), env=(51,), action=(2,)) -> dict:
    """Features as a LeRobot dataset's meta/info.json lists them (None: feature absent)."""
    feats = {"scene.seed": {"dtype": "int64", "shape": (1,), "names": None}}
    for key, shape in ((OBS_STATE, state), (OBS_ENV_STATE, env), (ACTION, action)):
        if shape is not None:
            feats[key] = {"dtype": "float32", "shape": shape, "names": None}
    return feats


def build_from_dataset(obstacle_encoding: str = "grid", **shapes) -> FormationDiffusionPolicy:
    """What lerobot-train's make_policy does with a dataset's features."""
    features = dataset_to_policy_features(dataset_features(**shapes))
    outputs = {k: f for k, f in features.items() if f.type is FeatureType.ACTION}
    inputs = {k: f for k, f in features.items() if k not in outputs}
    cfg = tiny_config(input_features=inputs, output_features=outputs, obstacle_encoding=obstacle_encoding)
    return FormationDiffusionPolicy(cfg)


def test_dataset_features_build():
    policy = build_from_dataset()
    assert policy.config.env_state_feature.shape == (51,)
    policy = build_from_dataset("grid+list", env=(66,))
    assert policy.config.env_state_feature.shape == (66,)


@pytest.mark.parametrize(
    "shapes, pattern",
    [
        ({"state": None}, r"needs the input feature 'observation.state' \(STATE, shape \(7,\)"),
        (
            {"env": None},
            r"needs the input feature 'observation.environment_state' \(ENV, shape \(51,\): obstacle_encoding 'grid'",
        ),
        ({"state": (9,)}, r"'observation.state' must have shape \(7,\) .*got \(9,\)"),
        (
            {"env": (49,)},
            r"'observation.environment_state' has shape \(49,\), but obstacle_encoding='grid' .* has \(51,\)",
        ),
        ({"action": (3,)}, r"needs the output feature 'action' \(ACTION, shape \(2,\)"),
        ({"action": None}, r"needs the output feature 'action'"),
    ],
)
def test_missing_or_misshaped_feature_names_it(shapes, pattern):
    with pytest.raises(ValueError, match=pattern):
        build_from_dataset(**shapes)


def test_error_lists_the_features_found():
    with pytest.raises(
        ValueError, match=r"Input features found: 'observation.state' \(STATE, shape \(7,\)\)"
    ):
        build_from_dataset(env=None)


def test_image_features_are_rejected():
    inputs, outputs = formation_features()
    inputs["observation.images.top"] = PolicyFeature(type=FeatureType.VISUAL, shape=(3, 64, 64))
    with pytest.raises(ValueError, match=r"takes no image features, got \['observation.images.top'\]"):
        FormationDiffusionPolicy(tiny_config(input_features=inputs, output_features=outputs))


@pytest.mark.parametrize(
    "overrides, pattern",
    [
        (
            {"horizon": 30},
            r"horizon=30 does not fit the U-Net: with down_dims=\[16, 32\] \(2 stages\) .* multiple of "
            r"2\*\*len\(down_dims\) = 4; nearest valid horizons: \[28, 32\]",
        ),
        (
            {"horizon": 4, "down_dims": (8, 16, 32)},
            r"horizon=4 does not fit .* = 8; nearest valid horizons: \[8\]",
        ),
    ],
)
def test_bad_horizon_is_explained(overrides, pattern):
    with pytest.raises(ValueError, match=pattern):
        tiny_config(**overrides)


def test_checkpoint_of_another_policy_type_is_refused(tmp_path):
    stock_diffusion_checkpoint(tmp_path)  # LeRobot's own diffusion policy
    with pytest.raises(TypeError, match=r"type 'formation_diffusion'.*DiffusionConfig \(type 'diffusion'\)"):
        FormationDiffusionPolicy.from_pretrained(tmp_path)


def test_non_config_is_refused():
    with pytest.raises(TypeError, match=r"needs a FormationDiffusionConfig, got dict \(type None\)"):
        FormationDiffusionPolicy({})


def test_observation_of_the_wrong_encoding_is_explained():
    """A "grid+list" policy evaluated on a "grid" env: say which --env.obstacle_encoding to use."""
    inputs, outputs = formation_features(env_dim=66)
    cfg = tiny_config(input_features=inputs, output_features=outputs, obstacle_encoding="grid+list")
    policy = FormationDiffusionPolicy(cfg).eval()
    obs = {OBS_STATE: torch.zeros(1, 7), OBS_ENV_STATE: torch.zeros(1, 51)}
    with pytest.raises(
        ValueError, match=r"has 51 values .* trained on 66. .*--env.obstacle_encoding=grid\+list"
    ):
        policy.select_action(obs)
