"""The generator's "policy" expert: a checkpoint with its safety layer as the demonstrator
(``data.pac_episodes.ExpertFactory``, ``bench.controllers.PolicyExpert``,
``lerobot-formation-generate --expert policy``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import dataset_file_hashes
from plugin_helpers import formation_features, save_nearest_checkpoint

from datasets_scripts import generate_pac_dataset as gen
from lerobot_formation.bench.controllers import PolicyExpert
from lerobot_formation.core.episodes.levels import get_level
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.core.world.sampling import sample_scenes
from lerobot_formation.data import lerobot_writer
from lerobot_formation.data.pac_episodes import EpisodeRecipe, Generator, check_expert, expert_rollout
from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy

REPO = "local/formation_self"
CEILING = get_level("level5").conditions


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    """A tiny untrained ``nearest+route`` checkpoint whose layer proposes route pursuit's chunk."""
    inputs, outputs = formation_features(env_dim=55)
    return save_nearest_checkpoint(
        tmp_path_factory.mktemp("ckpt") / "ckpt",
        input_features=inputs,
        output_features=outputs,
        obstacle_encoding="nearest+route",
        safety_horizon=5,
        num_inference_steps=2,
    )


def test_policy_expert_drives_the_layer_and_the_same_seed_gives_the_same_dataset(tmp_path, checkpoint):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    kw = dict(
        seed=3,
        obstacle_encoding="nearest+route",
        workers=0,
        progress=False,
        expert="policy",
        policy_expert=PolicyExpert(str(checkpoint)),
        randomize=CEILING,
    )
    a, b = tmp_path / "a", tmp_path / "b"
    lerobot_writer.generate(a, REPO, 1, **kw)  # one episode: the policy is sampled at every replan
    lerobot_writer.generate(b, REPO, 1, **kw)
    assert dataset_file_hashes(a) == dataset_file_hashes(b)
    ds = LeRobotDataset(REPO, root=a)
    assert ds.meta.total_episodes == 1
    meta = json.loads((a / "meta" / "generation.json").read_text())
    assert meta["expert"] == "policy" and meta["policy"] == f"diffusion-safe of {checkpoint} (K = 10)"
    actions = np.stack([np.asarray(ds[i]["action"]) for i in range(min(len(ds), 40))])
    assert np.isfinite(actions).all()


def test_policy_expert_runs_the_network_and_its_actions_are_not_pacs(checkpoint, monkeypatch):
    """The recorded commands are the layer's: the network is sampled (a counted call) and the actions
    differ from PAC's on the same scene."""
    calls = []
    sample = FormationDiffusionPolicy.sample_action_chunks

    def counted(self, *args, **kwargs):
        calls.append(1)
        return sample(self, *args, **kwargs)

    monkeypatch.setattr(FormationDiffusionPolicy, "sample_action_chunks", counted)
    params = FormationParams()
    scene = sample_scenes([3])
    layer = expert_rollout(scene, params, "nearest+route", CEILING, "policy", PolicyExpert(str(checkpoint)))
    pac = expert_rollout(scene, params, "nearest+route", CEILING, "pac")
    assert calls, "the policy's network was never sampled"
    n = min(int(layer.steps[0]), int(pac.steps[0]), 30)
    assert not np.allclose(layer.commands[0, :n], pac.commands[0, :n])


def test_policy_expert_arguments_are_checked(tmp_path, checkpoint, capsys):
    expert = PolicyExpert(str(checkpoint))
    with pytest.raises(ValueError, match="policy_expert"):
        check_expert("policy")
    with pytest.raises(ValueError, match="policy_expert"):
        check_expert("pac", expert)
    with pytest.raises(ValueError, match="policy_expert"):  # a recipe is checked when made
        EpisodeRecipe(expert="policy")
    with pytest.raises(ValueError, match="workers must be 0, got 2"):
        Generator(FormationParams(), EpisodeRecipe(expert="policy", policy_expert=expert), workers=2)
    with pytest.raises(ValueError, match="'route-pursuit' runs no checkpoint"):
        PolicyExpert(str(checkpoint), controller="route-pursuit")
    base = ["--episodes", "1", "--root", str(tmp_path / "d"), "--repo-id", REPO]
    cases = [
        (["--expert", "policy"], "--expert policy needs --policy.path"),
        (["--policy.path", str(checkpoint)], "only read by --expert policy, got --expert pac"),
        (["--expert", "policy", "--policy.path", str(tmp_path / "nowhere")], "nowhere is not a folder"),
        (
            ["--expert", "policy", "--policy.path", str(checkpoint), "--workers", "1"],
            "give --workers 0, got 1",
        ),
    ]
    for extra, message in cases:
        with pytest.raises(SystemExit):
            gen.parse_args([*base, *extra])
        assert message in capsys.readouterr().err
    assert not (tmp_path / "d").exists()


def test_every_expert_has_a_name_for_the_summary_line():
    """The summary line (printed after the dataset is written) names the expert: a new entry of
    ``EXPERTS`` without a name would fail there, after the work."""
    from lerobot_formation.data.pac_episodes import EXPERTS

    assert set(gen.EXPERT_NAMES) == set(EXPERTS)
    for expert in EXPERTS:
        line = gen.summary_line(
            {
                "expert": expert,
                "pac_attempted": 4,
                "pac_succeeded": 3,
                "pac_success_rate": 0.75,
                "episodes": 3,
                "frames": 9,
                "mb": 0.1,
                "seconds": 1.0,
            },
            "out",
        )
        assert gen.EXPERT_NAMES[expert] in line
