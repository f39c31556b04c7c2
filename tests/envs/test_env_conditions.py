"""Realistic conditions through the env, the vector env, the env config (``--env.<field>``), the
bench and the generator: the same episode path as the engine (``core.episodes.rollout.Teams``)."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json

import draccus
import numpy as np
import pytest

from lerobot_formation.core.controllers.pac import PACController
from lerobot_formation.core.episodes.rollout import rollout
from lerobot_formation.core.perception.conditions import (
    CONDITION_FIELDS,
    CONDITION_TYPES,
    Conditions,
    condition_help,
)
from lerobot_formation.core.world.sampling import sample_scenes
from lerobot_formation.core.world.scene_files import scenes_from_list
from lerobot_formation.envs.condition_flags import add_condition_arguments, conditions_from_flags
from lerobot_formation.envs.env import FormationEnv
from lerobot_formation.envs.env_config import FormationEnvConfig
from lerobot_formation.envs.vector_env import FormationVectorEnv

ALL_ON = Conditions(
    sensing_range=2.0,
    obstacle_noise=0.03,
    pose_noise=0.02,
    action_noise=0.1,
    action_delay=2,
    max_linear_accel=1.0,
    max_angular_accel=4.0,
    moving_obstacles=1,
    obstacle_speed=0.2,
)


def test_env_config_fields_from_the_command_line():
    cfg = draccus.parse(
        FormationEnvConfig,
        args=["--sensing_range=3", "--action_delay=2", "--moving_obstacles=1", "--obstacle_speed=0.2"],
    )
    assert cfg.conditions() == Conditions(
        sensing_range=3.0, action_delay=2, moving_obstacles=1, obstacle_speed=0.2
    )
    env = cfg.make_env_factory()()
    assert env.unwrapped.conditions == cfg.conditions()
    env.close()
    assert "conditions" not in FormationEnvConfig().gym_kwargs  # off: the env kwargs of before
    with pytest.raises(ValueError, match="env.action_delay must be an integer >= 0, got -1"):
        FormationEnvConfig(action_delay=-1)


def test_every_condition_is_an_env_field_and_a_flag():
    """Each field of ``Conditions`` (declared once, with its help) is a field of the env config with
    its type, default and help (draccus's ``--env.<field>``) and a flag of the bench and the generator
    (``add_condition_arguments``) with its help; ALL_ON goes through both to the same conditions."""
    env_fields = {f.name: f for f in dataclasses.fields(FormationEnvConfig)}
    off = Conditions()
    ap = argparse.ArgumentParser()
    add_condition_arguments(ap)
    flags = {a.option_strings[0]: a for a in ap._actions if a.option_strings[0].startswith("--env.")}
    assert set(flags) == {f"--env.{name}" for name in CONDITION_FIELDS}
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), pytest.raises(SystemExit):
        draccus.parse(FormationEnvConfig, args=["--help"])
    draccus_help = " ".join(buf.getvalue().split())
    for name in CONDITION_FIELDS:
        assert name in env_fields, f"the env config lacks the condition field {name}"
        assert env_fields[name].default == getattr(off, name)
        assert env_fields[name].type == CONDITION_TYPES[name]
        assert f"--{name} " in draccus_help and " ".join(condition_help(name).split()) in draccus_help
        assert flags[f"--env.{name}"].help == condition_help(name) and flags[f"--env.{name}"].default is None
    on = {name: getattr(ALL_ON, name) for name in CONDITION_FIELDS}
    assert FormationEnvConfig(**on).conditions() == ALL_ON
    argv = [item for name, value in on.items() for item in (f"--env.{name}", str(value))]
    assert conditions_from_flags(ap.parse_args(argv)) == ALL_ON
    cfg = draccus.parse(FormationEnvConfig, args=[f"--{name}={value}" for name, value in on.items()])
    assert cfg.conditions() == ALL_ON


@pytest.mark.parametrize("encoding", ["nearest", "nearest+route"])
def test_env_observes_what_the_engine_observes(encoding):
    """PAC stepping the env on its perception takes the engine's actions, and the observations the
    engine records (the dataset's) are the env's (the route hint on the same map snapshot)."""
    scenes = sample_scenes([1_000_000])
    rec = rollout(
        scenes, PACController(), max_steps=120, conditions=ALL_ON, record_observations=(encoding, None)
    )
    env = FormationEnv(obstacle_encoding=encoding, conditions=ALL_ON)
    obs, _ = env.reset(seed=1_000_000)
    ctrl = PACController()
    ctrl.reset(env.teams.perceive())
    for t in range(int(rec.steps[0])):
        np.testing.assert_array_equal(obs["environment_state"], rec.observations["environment_state"][0, t])
        np.testing.assert_array_equal(obs["agent_pos"], rec.observations["agent_pos"][0, t])
        command = ctrl.act(env.teams.perceive(), np.array([0]))[0]
        np.testing.assert_array_equal(command, rec.commands[0, t])
        obs, _, term, _, info = env.step(command)
        if term:
            break
    assert env.render() is None  # no render mode


def test_env_hides_unsensed_obstacles_from_the_observation():
    scene = {"obstacles": [[2.0, 5.0, 0.5]], "goal": [0.0, 10.0], "start": [0.0, 0.0, np.pi / 2]}
    env = FormationEnv(
        obstacle_encoding="nearest", conditions=Conditions(sensing_range=1.2), render_mode="rgb_array"
    )
    obs, _ = env.reset(options={"scene": scene})
    present = []
    for _ in range(120):
        present.append(obs["environment_state"][2 + 3])  # slot 0's present flag
        obs, *_ = env.step(np.array([0.5, 0.0], np.float32))
    present = np.array(present)
    first = int(np.argmax(present))
    assert 0 < first and not present[:first].any() and present[first:].all()
    assert env.render().dtype == np.uint8


@pytest.mark.parametrize("encoding", ["nearest+velocity", "nearest+route+velocity"])
def test_vector_env_with_conditions_matches_single_envs(encoding):
    actions = np.random.default_rng(1).uniform([0.2, -0.5], [0.6, 0.5], size=(30, 2, 2)).astype(np.float32)
    venv = FormationVectorEnv(2, obstacle_encoding=encoding, conditions=ALL_ON)
    obs, _ = venv.reset(seed=7)
    singles = [FormationEnv(obstacle_encoding=encoding, conditions=ALL_ON) for _ in range(2)]
    single_obs = [e.reset(seed=7 + i)[0] for i, e in enumerate(singles)]
    ended = np.zeros(2, bool)
    for a in actions:
        for i in range(2):
            if not ended[i]:
                np.testing.assert_array_equal(obs["environment_state"][i], single_obs[i]["environment_state"])
        obs, _, term, trunc, _ = venv.step(a)
        for i, e in enumerate(singles):
            if not ended[i]:
                single_obs[i], _, t, _, _ = e.step(a[i])
                ended[i] |= t
        assert not (term & ~ended).any()


def test_scenes_file_velocities_round_trip(tmp_path):
    from lerobot_formation.core.world.scene_files import load_scenes, save_scenes

    scenes = scenes_from_list(
        [{"obstacles": [[3.0, 5.0, 0.5]], "goal": [0.0, 10.0], "velocities": [[0.1, -0.2]]}]
    )
    save_scenes(scenes, tmp_path / "s.json")
    back = load_scenes(tmp_path / "s.json")
    np.testing.assert_array_equal(back.velocities, scenes.velocities)
    with pytest.raises(ValueError, match="velocities must be a list"):
        scenes_from_list([{"obstacles": [[3.0, 5.0, 0.5]], "goal": [0.0, 10.0], "velocities": []}])
    with pytest.raises(ValueError, match="at most 10 m/s"):
        scenes_from_list([{"obstacles": [[3.0, 5.0, 0.5]], "goal": [0.0, 10.0], "velocities": [[50, 0]]}])


def test_bench_takes_condition_flags(tmp_path, capsys):
    from lerobot_formation.bench import cli as bench

    out = tmp_path / "b"
    argv = [
        "--controllers",
        "pac",
        "--scenes",
        "random:2",
        "--out",
        str(out),
        "--no-figures",
        "--no-progress",
    ]
    assert bench.main([*argv, "--env.sensing_range", "2", "--env.action_delay", "1"]) == 0
    meta = json.loads((out / "results.json").read_text())["meta"]
    assert meta["conditions"] == {"sensing_range": 2.0, "action_delay": 1}
    with pytest.raises(SystemExit) as e:
        bench.main([*argv, "--env.obstacle_noise", "-1"])
    assert e.value.code == 2
    assert "--env.obstacle_noise must be a finite number >= 0, got -1.0" in capsys.readouterr().err


def test_generator_under_conditions(tmp_path):
    from datasets_scripts import generate_pac_dataset

    root = tmp_path / "ds"
    argv = ["--episodes", "1", "--root", str(root), "--repo-id", "local/c", "--workers", "0", "--no-progress"]
    assert (
        generate_pac_dataset.main([*argv, "--obstacle-encoding", "nearest", "--env.sensing_range", "2"]) == 0
    )
    summary = json.loads((root / "meta" / "generation.json").read_text())
    assert summary["conditions"] == {"sensing_range": 2.0}
    with pytest.raises(SystemExit):
        generate_pac_dataset.parse_args([*argv, "--env.action_delay", "x"])


def test_episode_metrics_see_moving_obstacles_and_executed_actions():
    from lerobot_formation.envs.episode_metrics import INFO_KEY, FormationEpisodeMetrics

    crossing = {"obstacles": [[-4.0, 5.0, 0.5]], "goal": [0.0, 10.0], "velocities": [[0.4, 0.0]]}
    env = FormationEpisodeMetrics(FormationEnv(conditions=Conditions(action_delay=3)))
    env.reset(options={"scene": crossing})
    for _ in range(300):
        _, _, term, _, info = env.step(np.array([0.5, 0.0], np.float32))
        if term:
            break
    metrics = info[INFO_KEY]
    assert metrics["outcome"] == "collision"
    assert metrics["formation_min_clearance"] < 0.0  # against where the obstacle was, not where it started
    np.testing.assert_array_equal(env.unwrapped.applied_action, [[0.5, 0.0]])


def test_episode_metrics_flag_a_mover_that_strikes_a_standing_team():
    """``struck_by_mover`` (core.episodes.metrics.mover_strikes) in lerobot-eval's per-episode record: the team
    leaves the start zone (movers bounce off it), stops, and a crossing obstacle runs into it."""
    from lerobot_formation.envs.episode_metrics import INFO_KEY, FormationEpisodeMetrics

    crossing = {"obstacles": [[-6.0, 4.2, 0.5]], "goal": [0.0, 10.0], "velocities": [[0.4, 0.0]]}
    outcomes = {}
    for stop_after in (75, None):  # stand from step 75 on (the leaders at y = 3.75), or drive on
        env = FormationEpisodeMetrics(FormationEnv())
        env.reset(options={"scene": crossing})
        for t in range(300):
            v = 0.0 if stop_after is not None and t >= stop_after else 0.5
            _, _, term, _, info = env.step(np.array([v, 0.0], np.float32))
            if term:
                break
        outcomes[stop_after] = info[INFO_KEY]
    standing = outcomes[75]
    assert standing["outcome"] == "collision" and standing["struck_by_mover"] is True
    assert isinstance(outcomes[None]["struck_by_mover"], bool)
