"""scripts/derive_checkpoint.py: options changed, weights and every other file kept, in place too."""

import importlib.util
import json
from pathlib import Path

import pytest
from plugin_helpers import save_nearest_checkpoint

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "derive_checkpoint.py"


def _derive(*argv: str) -> int:
    spec = importlib.util.spec_from_file_location("derive_checkpoint", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main(list(argv))


def test_set_changes_config_fields_in_place_and_keeps_the_other_files(tmp_path):
    from lerobot_formation.policy.checkpoint import load_policy

    ckpt = save_nearest_checkpoint(tmp_path / "ckpt")
    (ckpt / "dataset_scenes.json").write_text('{"scenes": []}')
    before = {p.name: p.read_bytes() for p in ckpt.iterdir()}
    config = json.loads(before["config.json"])
    assert config["safety_margin"] == 0.1 and config["inference_backend"] == "eager"

    assert (
        _derive(str(ckpt), str(ckpt), "--set", "safety_margin=0.05", "--set", "inference_backend=trace") == 0
    )

    after = {p.name: p.read_bytes() for p in ckpt.iterdir()}
    assert set(after) == set(before)
    changed = json.loads(after["config.json"])
    assert list(changed) == list(config)  # same fields, same order
    assert changed == {**config, "safety_margin": 0.05, "inference_backend": "trace"}
    # the weights, the extra file and the processors (same steps, same statistics) byte for byte
    assert all(after[name] == data for name, data in before.items() if name != "config.json")
    policy, _, _ = load_policy(ckpt)
    assert policy.config.safety_margin == 0.05 and policy.config.inference_backend == "trace"
    assert not list(tmp_path.glob(".ckpt.tmp*"))


def test_set_changes_a_field_of_the_known_world(tmp_path):
    from lerobot_formation.core.safety.layer import KnownWorld
    from lerobot_formation.policy.checkpoint import load_policy

    ckpt = save_nearest_checkpoint(tmp_path / "ckpt")
    argv = ["--set", "safety_world.action_delay=1", "--set", "safety_world.moving_obstacles=true"]
    assert _derive(str(ckpt), str(ckpt), *argv) == 0
    assert json.loads((ckpt / "config.json").read_text())["safety_world"]["action_delay"] == 1
    policy, _, _ = load_policy(ckpt)
    assert policy.config.safety_world == KnownWorld(moving_obstacles=True, action_delay=1)
    with pytest.raises(SystemExit, match=r"safety_world.action_delay must be an integer >= 0"):
        _derive(str(ckpt), str(tmp_path / "new"), "--set", "safety_world.action_delay=-1")
    assert not (tmp_path / "new").exists()


def test_set_with_an_unknown_field_is_refused_and_writes_nothing(tmp_path):
    ckpt = save_nearest_checkpoint(tmp_path / "ckpt")
    with pytest.raises(SystemExit, match="expected FIELD=VALUE with a formation_diffusion config field"):
        _derive(str(ckpt), str(tmp_path / "new"), "--set", "no_such_field=1")
    assert not (tmp_path / "new").exists()


def _route_checkpoint(path):
    from plugin_helpers import formation_features

    inputs, _ = formation_features(env_dim=55)
    return save_nearest_checkpoint(path, obstacle_encoding="nearest+route", input_features=inputs)


def test_a_new_encoding_widens_the_network_and_it_acts_as_before(tmp_path):
    """nearest+route -> nearest+route+velocity: the velocity columns get zero weights, every other
    weight moves with its feature, so the denoiser's output is the old one's whatever the velocities."""
    import torch

    from lerobot_formation.policy.checkpoint import load_policy

    ckpt = _route_checkpoint(tmp_path / "ckpt")
    assert (
        _derive(str(ckpt), str(tmp_path / "wide"), "--set", "obstacle_encoding=nearest+route+velocity") == 0
    )
    old, _, _ = load_policy(ckpt)
    new, _, _ = load_policy(tmp_path / "wide")
    assert new.config.obstacle_encoding == "nearest+route+velocity"
    assert tuple(new.config.input_features["observation.environment_state"].shape) == (79,)

    g = torch.Generator().manual_seed(0)
    B, n_obs = 3, old.config.n_obs_steps
    state, env = torch.rand(B, n_obs, 7, generator=g), torch.rand(B, n_obs, 55, generator=g)
    velocity = 5 * torch.randn(B, n_obs, 24, generator=g)  # large: zero weights must ignore them
    wide_env = torch.cat([env[..., :50], velocity, env[..., 50:]], dim=-1)  # rows, velocities, route
    x = torch.randn(B, old.config.horizon, 2, generator=g)
    t = torch.tensor([0, 40, 99])
    with torch.no_grad():
        before = old.diffusion.unet(x, t, global_cond=torch.cat([state, env], -1).flatten(1))
        after = new.diffusion.unet(x, t, global_cond=torch.cat([state, wide_env], -1).flatten(1))
        # the route part moved: a network that read the old positions would differ
        shuffled = new.diffusion.unet(
            x, t, global_cond=torch.cat([state, torch.cat([env, velocity], -1)], -1).flatten(1)
        )
    torch.testing.assert_close(after, before, rtol=1e-5, atol=1e-5)
    assert not torch.allclose(shuffled, before, atol=1e-3)


def test_widening_to_an_encoding_without_the_old_features_is_refused(tmp_path):
    ckpt = _route_checkpoint(tmp_path / "ckpt")
    with pytest.raises(SystemExit, match=r"lacks 5 feature\(s\) of the old one, e.g. \['route_near_bx'"):
        _derive(str(ckpt), str(tmp_path / "new"), "--set", "obstacle_encoding=nearest+velocity")
    assert not (tmp_path / "new").exists()
