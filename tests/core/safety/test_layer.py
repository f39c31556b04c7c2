"""``core.safety.layer``: the settings object (defaults, checks, the one mapping to config fields), what
the layer is told of the world (``KnownWorld``) and the layer's own per-episode state and counts, on
numpy arrays alone."""

import dataclasses

import numpy as np
import pytest

from lerobot_formation.core.encodings.obstacle_grid import environment_state
from lerobot_formation.core.perception.conditions import Conditions
from lerobot_formation.core.safety.layer import (
    CONFIG_FIELDS,
    LAYER_STAT_KEYS,
    KnownWorld,
    SafetyLayer,
    SafetySettings,
    WorldError,
    known_world,
)


def _env(obstacles, goal=(0.0, 8.0), encoding="nearest+route"):
    obs = np.array([obstacles], dtype=np.float64)
    pose = np.array([[0.0, 0.0, np.pi / 2]])
    return environment_state(obs, obs[..., 2] > 0, np.array([goal]), encoding, pose=pose)


def test_each_setting_maps_to_one_config_field_and_back():
    assert set(CONFIG_FIELDS) == {f.name for f in dataclasses.fields(SafetySettings)}
    assert list(CONFIG_FIELDS) == ["filter", "margin", "horizon", "mover_uncertainty", "world", "search"]
    assert len(set(CONFIG_FIELDS.values())) == len(CONFIG_FIELDS)
    assert SafetySettings.config_fields(margin=0.1, horizon=0) == {"safety_margin": 0.1, "safety_horizon": 0}
    assert SafetySettings.from_config_fields({"safety_margin": 0.1, "horizon": 16}) == {"margin": 0.1}
    with pytest.raises(ValueError, match="unknown safety settings"):
        SafetySettings.config_fields(safety_margin=0.1)

    class Config:  # any object with the config's field names
        pass

    config = Config()
    for name, source in CONFIG_FIELDS.items():
        setattr(config, source, getattr(SafetySettings(), name))
    config.safety_margin = 0.2
    assert SafetySettings.from_config(config) == SafetySettings(margin=0.2)


@pytest.mark.parametrize(
    "bad",
    [
        {"filter": "qp"},
        {"margin": -0.1},
        {"horizon": True},
        {"horizon": 1.5},
        {"mover_uncertainty": float("nan")},
        {"world": {"action_delay": 1}},
    ],
)
def test_a_bad_setting_is_refused_by_name(bad):
    (name,) = bad
    with pytest.raises(ValueError, match=rf"{name} \({CONFIG_FIELDS[name]}\) must be"):
        SafetySettings(**bad)


@pytest.mark.parametrize(
    ("bad", "want"),
    [
        ({"moving_obstacles": 1}, "true or false"),
        ({"action_delay": 1.5}, r"an integer >= 0 \[control steps\]"),
        ({"action_delay": -1}, r"an integer >= 0 \[control steps\]"),
        ({"max_linear_accel": 0.0}, r"null \(no limit\) or a finite number > 0"),
        ({"max_angular_accel": float("inf")}, r"null \(no limit\) or a finite number > 0"),
        ({"obstacle_noise": -0.02}, "a finite std >= 0"),
        ({"pose_noise": float("nan")}, "a finite std >= 0"),
    ],
)
def test_a_bad_known_world_is_refused_naming_field_and_value(bad, want):
    ((name, value),) = bad.items()
    with pytest.raises(WorldError, match=rf"^safety_world\.{name} must be {want}, got {value!r}$"):
        KnownWorld(**bad)
    assert WorldError.config_error and issubclass(WorldError, ValueError)  # one line on the CLI


def test_the_known_world_of_conditions():
    assert known_world(None) is None and known_world(Conditions()) is None  # nothing to tell
    assert known_world(None, scenes_move=True) == KnownWorld(moving_obstacles=True)
    told = known_world(
        Conditions(
            action_delay=1, max_linear_accel=0.5, pose_noise=0.02, moving_obstacles=2, obstacle_speed=0.3
        )
    )
    assert told == KnownWorld(moving_obstacles=True, action_delay=1, max_linear_accel=0.5, pose_noise=0.02)


def test_the_layer_owns_its_episodes_state_and_counts():
    world = KnownWorld(action_delay=2, moving_obstacles=True, obstacle_noise=0.05)
    layer = SafetyLayer(SafetySettings(world=world))
    layer.reset(3)
    assert layer.in_flight.shape == (3, 2, 2) and layer.executed_velocity.shape == (3, 2)
    assert layer.tracker is not None and layer.smoother is not None
    assert layer.stats == dict.fromkeys(LAYER_STAT_KEYS, 0)
    layer.send(np.array([1]), np.array([[9.0, 0.5]]))  # clipped to the action bounds
    np.testing.assert_allclose(layer.in_flight[1, -1], [0.6, 0.5])
    assert not layer.in_flight[[0, 2]].any()
    view = layer.view(np.repeat(_env([[1.0, 2.0, 0.3]]), 2, axis=0), np.array([0, 2]))
    assert view.start.steps == 2 and len(view.goal) == 2
    assert SafetyLayer().tracker is None  # nothing before ``start``


def test_choose_recheck_and_filter_count_what_the_layer_did():
    layer = SafetyLayer(SafetySettings(search=0))  # the search would find a way round the wall
    layer.reset(1)
    wall = _env([[x, 0.9, 0.3] for x in np.linspace(-1.5, 1.5, 7)])
    straight = np.tile([0.5, 0.0], (1, 2, 15, 1))  # both samples drive into the wall
    chosen, info = layer.choose(wall, straight)
    assert chosen.shape == (1, 15, 2) and not info["any_safe"][0]
    assert layer.stats["replans_none_safe"] == 1
    assert layer.stats["escapes"] + layer.stats["proposals"] + layer.stats["stops"] <= 1
    assert not layer.recheck(layer.observed_obstacles(wall), straight[:, 0])[0]
    assert layer.stats["rechecks_failed"] == 1
    close = _env([[x, 0.5, 0.3] for x in np.linspace(-1.5, 1.5, 7)])  # 5 cm from the leaders' margin
    filtered, changed = layer.filter(close, np.array([[0.6, 0.0]]))
    assert changed[0] and filtered[0, 0] < 0.6 and layer.stats["filter_interventions"] == 1
    off = SafetyLayer(SafetySettings(filter="none"))
    same, changed = off.filter(close, np.array([[0.6, 0.0]]))
    assert not changed[0] and same[0, 0] == 0.6 and off.stats["filter_interventions"] == 0
    layer.reset()
    assert layer.stats == dict.fromkeys(LAYER_STAT_KEYS, 0)


def test_the_search_joins_the_candidates_only_where_obstacles_move():
    wall = _env([[x, 0.9, 0.3] for x in np.linspace(-1.5, 1.5, 7)])
    straight = np.tile([0.5, 0.0], (1, 2, 15, 1))  # both samples drive into the wall
    static, moving = SafetyLayer(), SafetyLayer(SafetySettings(world=KnownWorld(moving_obstacles=True)))
    static.reset(1)
    moving.reset(1)
    _, alone = static.choose(wall, straight)
    _, searched = moving.choose(wall, straight)
    assert searched["safe"].shape[1] == alone["safe"].shape[1] + SafetySettings().search
    assert not alone["search_kept"].any() and static.stats["searched"] == 0
    assert searched["safe"][0, alone["safe"].shape[1] :].any()  # a search path goes round the wall
    assert moving.stats["searched"] == int(searched["search_kept"].sum())
