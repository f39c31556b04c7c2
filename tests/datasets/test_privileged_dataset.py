"""The generator's privileged expert and randomized conditions (``data.pac_episodes``)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import dataset_file_hashes

from datasets_scripts import generate_pac_dataset as gen
from lerobot_formation.core.episodes.levels import get_level
from lerobot_formation.core.perception.conditions import randomized_conditions
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.core.world.sampling import sample_scenes
from lerobot_formation.data import lerobot_writer
from lerobot_formation.data.dataset_frames import episode_frames
from lerobot_formation.data.pac_episodes import CONDITION_GROUP, EpisodeRecipe, expert_rollout, simulate_batch

REPO = "local/formation_priv"
CEILING = get_level("level5").conditions


def test_randomized_conditions_follow_the_seed_and_vary_across_groups():
    assert CONDITION_GROUP == 16  # seeds 15 and 16 are in different groups
    params = FormationParams()
    first = randomized_conditions(CEILING, 15 // CONDITION_GROUP)
    assert first != randomized_conditions(CEILING, 16 // CONDITION_GROUP)
    recipe = EpisodeRecipe("nearest", expert="privileged", randomize=CEILING)
    both = simulate_batch(np.array([15, 16]), None, params, recipe)
    alone = simulate_batch(np.array([16]), None, params, recipe)
    assert both[0] == 2 and len(both[1]) == 2 and len(alone[1]) == 1
    for key, value in alone[1][0].items():  # seed 16's episode does not depend on its batch
        np.testing.assert_array_equal(both[1][1][key], value, err_msg=key)
    scene = sample_scenes([15])
    rec = expert_rollout(scene, params, "nearest", first, "privileged")
    for key, value in episode_frames(rec, scene, 0, "nearest").items():  # seed 15: its group's draw
        np.testing.assert_array_equal(both[1][0][key], value, err_msg=key)
    assert not np.array_equal(both[1][0]["action"][:5], both[1][1]["action"][:5])


def test_same_seed_same_privileged_randomized_dataset(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    kw = dict(seed=14, obstacle_encoding="nearest", workers=0, progress=False, expert="privileged")
    a, b = tmp_path / "a", tmp_path / "b"
    lerobot_writer.generate(a, REPO, 1, randomize=CEILING, **kw)  # batch independence: the test above
    lerobot_writer.generate(b, REPO, 1, randomize=CEILING, **kw)
    assert dataset_file_hashes(a) == dataset_file_hashes(b)
    ds = LeRobotDataset(REPO, root=a)
    assert ds.meta.total_episodes == 1
    meta = json.loads((a / "meta" / "generation.json").read_text())
    assert meta["expert"] == "privileged"
    assert meta["conditions_randomize"]["ceiling"] == CEILING.changed()
    with pytest.raises(ValueError, match="exclude each other"):
        lerobot_writer.generate(tmp_path / "c", REPO, 3, randomize=CEILING, conditions=CEILING, **kw)


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["--expert", "sage"], "invalid choice"),
        (["--conditions-randomize", "level3"], "has no conditions to randomize"),
        (["--conditions-randomize", "level9"], "unknown level"),
        (["--conditions-randomize", "level5", "--env.pose_noise", "0.1"], "excludes --env.* flags"),
        (["--scene-preset", "paper,nope"], "'nope' of 'paper,nope' is neither a preset"),
    ],
)
def test_bad_arguments(argv, match, capsys):
    with pytest.raises(SystemExit):
        gen.parse_args(argv)
    assert match in capsys.readouterr().err


def test_mixtures_are_accepted():
    args = gen.parse_args(["--scene-preset", "structures"])
    assert args.scene_preset == "structures"
    args = gen.parse_args(["--scene-preset", "paper,wide,mixed-hard,structures", "--expert", "privileged"])
    assert args.expert == "privileged"


def test_route_velocity_frames_are_the_route_frames_with_the_movers_velocities():
    """Recorded with ``nearest+route+velocity`` under moving obstacles: the same expert and commands as
    a ``nearest+route`` recording of the seed, its rows and route the same, and the velocities of the
    moving obstacles the team observed in between."""
    params = FormationParams()
    level5 = get_level("level5").conditions
    seeds = np.array([16, 17])
    both = simulate_batch(
        seeds, None, params, EpisodeRecipe("nearest+route+velocity", expert="privileged", conditions=level5)
    )
    route = simulate_batch(
        seeds, None, params, EpisodeRecipe("nearest+route", expert="privileged", conditions=level5)
    )
    key = "observation.environment_state"
    moving = 0
    for a, b in zip(both[1], route[1], strict=True):
        np.testing.assert_array_equal(a["action"], b["action"])
        assert a[key].shape[1] == 79 and b[key].shape[1] == 55
        np.testing.assert_array_equal(a[key][:, :50], b[key][:, :50])
        np.testing.assert_array_equal(a[key][:, 74:], b[key][:, 50:])
        speeds = np.linalg.norm(a[key][:, 50:74].reshape(len(a[key]), 12, 2), axis=-1)
        assert speeds.max() <= level5.obstacle_speed + 1e-6
        moving += int((speeds > 0.1).any(axis=1).sum())
    assert moving > 0  # some frames observed a mover


def test_the_oracle_expert_records_its_plans():
    """``expert="oracle"``: the episodes the oracle solved, their actions its plan as sent."""
    from lerobot_formation.core.episodes.oracle import OracleController

    params = FormationParams()
    recipe = EpisodeRecipe("nearest", expert="oracle")
    attempted, frames = simulate_batch(np.array([3, 4]), None, params, recipe)
    assert attempted == 2 and len(frames) == 2
    oracle = OracleController(params=params)
    oracle.plan_episodes(sample_scenes([3, 4]), None, params.max_steps)
    for b, episode in enumerate(frames):
        n = len(episode["action"])
        np.testing.assert_allclose(episode["action"], oracle.plans.commands[b, :n], atol=1e-6)
