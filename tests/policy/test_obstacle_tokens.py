"""The obstacle-token encoder (``obstacle_encoder="tokens"``): invariances, empty scenes, the config's
checks, the "flat" model unchanged, and a tiny tokens policy through every sampler."""

import json
from pathlib import Path

import draccus
import pytest
import torch
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.configs.train import TrainPipelineConfig
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_formation.compat.lerobot_compat import global_conditioning, stock_global_conditioning
from lerobot_formation.core.encodings.obstacle_grid import environment_state_dim, get_encoding
from lerobot_formation.envs.env_config import FormationEnvConfig
from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig
from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy
from lerobot_formation.policy.obstacle_tokens import ObstacleTokenEncoder, token_layout

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
ENCODING = "nearest+route+velocity"
SLOTS = 12
HORIZON, N_OBS = 16, 2


def tiny_config(encoding: str = ENCODING, **overrides) -> FormationDiffusionConfig:
    kwargs = dict(
        device="cpu",
        push_to_hub=False,
        input_features={
            OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(7,)),
            OBS_ENV_STATE: PolicyFeature(type=FeatureType.ENV, shape=(environment_state_dim(encoding),)),
        },
        output_features={ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(2,))},
        obstacle_encoding=encoding,
        obstacle_encoder="tokens",
        token_dim=8,
        horizon=HORIZON,
        n_obs_steps=N_OBS,
        n_action_steps=8,
        down_dims=(16, 32),
        kernel_size=3,
        n_groups=4,
        diffusion_step_embed_dim=16,
        noise_scheduler_type="DDIM",
        num_inference_steps=3,
        # standard sampling: one sample, no safety layer, guidance, warm start or smoothing
        num_candidates=1,
        safety_filter="none",
        sampling_guidance=0.0,
        safety_horizon=0,
        warm_start_step=0,
        chunk_smoothing=0,
        inference_backend="eager",
    )
    kwargs.update(overrides)
    return FormationDiffusionConfig(**kwargs)


def scene(batch: int, present: int, slots: int = SLOTS, seed: int = 0) -> torch.Tensor:
    """Environment states (batch, D) of ``nearest+route+velocity`` with the first ``present`` slots
    filled (metres, as the IDENTITY normalisation leaves them) and zeros elsewhere."""
    g = torch.Generator().manual_seed(seed)
    rows = torch.zeros(batch, slots, 4)
    rows[:, :present, :2] = torch.randn(batch, present, 2, generator=g) * 2
    rows[:, :present, 2] = torch.rand(batch, present, generator=g) * 0.8
    rows[:, :present, 3] = 1.0
    velocity = torch.zeros(batch, slots, 2)
    velocity[:, :present] = torch.randn(batch, present, 2, generator=g) * 0.3
    goal, route = torch.randn(batch, 2, generator=g), torch.randn(batch, 5, generator=g)
    return torch.cat([goal, rows.flatten(1), velocity.flatten(1), route], dim=1)


def permute_slots(env: torch.Tensor, order: torch.Tensor, slots: int = SLOTS) -> torch.Tensor:
    rows = env[:, 2 : 2 + 4 * slots].reshape(-1, slots, 4)[:, order]
    velocity = env[:, 2 + 4 * slots : 2 + 6 * slots].reshape(-1, slots, 2)[:, order]
    return torch.cat([env[:, :2], rows.flatten(1), velocity.flatten(1), env[:, 2 + 6 * slots :]], dim=1)


def encoder(slots: int = SLOTS, layers: int = 2, seed: int = 0) -> ObstacleTokenEncoder:
    torch.manual_seed(seed)
    layout = token_layout(get_encoding(ENCODING), slots)
    return ObstacleTokenEncoder(7, layout, dim=16, layers=layers).eval()


def test_permutation_of_the_slots_changes_nothing():
    enc, state, env = encoder(), torch.randn(5, 7), scene(5, present=7)
    order = torch.randperm(SLOTS, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(enc(state, permute_slots(env, order)), enc(state, env), rtol=0, atol=1e-6)


def test_an_absent_slot_is_ignored_whatever_it_holds():
    enc, state, env = encoder(), torch.randn(5, 7), scene(5, present=4)
    garbage = env.clone()
    for k in (4, 9):  # empty slots: position, radius and velocity set to anything, present stays 0
        garbage[:, 2 + 4 * k : 5 + 4 * k] = torch.tensor([1e6, float("nan"), -3.0])
        garbage[:, 2 + 4 * SLOTS + 2 * k : 4 + 4 * SLOTS + 2 * k] = float("inf")
    assert torch.equal(enc(state, garbage), enc(state, env))


def test_the_weights_do_not_depend_on_the_slot_count():
    """The same weights read 12 or 20 slots; 8 more empty slots change nothing."""
    small, large = encoder(SLOTS), encoder(20, seed=1)
    large.load_state_dict(small.state_dict())
    state, env = torch.randn(3, 7), scene(3, present=6)
    wide = torch.zeros(3, 2 + 6 * 20 + 5)  # the same obstacles in 20 slots
    wide[:, :2] = env[:, :2]
    wide[:, 2 : 2 + 4 * SLOTS] = env[:, 2 : 2 + 4 * SLOTS]
    wide[:, 2 + 4 * 20 : 2 + 4 * 20 + 2 * SLOTS] = env[:, 2 + 4 * SLOTS : 2 + 6 * SLOTS]
    wide[:, -5:] = env[:, -5:]
    torch.testing.assert_close(large(state, wide), small(state, env), rtol=0, atol=1e-6)


def test_no_obstacle_gives_finite_features_and_gradients():
    enc = encoder().train()
    state, env = torch.randn(4, 7), scene(4, present=0)
    out = enc(state, env)
    assert torch.isfinite(out).all()
    assert torch.equal(out[:, 16:], torch.zeros(4, 16))  # the pool of no obstacle is 0
    out.square().sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in enc.parameters() if p.grad is not None)
    # one present obstacle in one row: the empty rows are unchanged by it
    env[0, 2:6] = torch.tensor([1.0, 2.0, 0.3, 1.0])
    torch.testing.assert_close(enc(state, env)[1:], out[1:].detach(), rtol=0, atol=1e-6)


def test_tokens_config_errors_name_the_field_and_the_value():
    with pytest.raises(ValueError) as bad:
        tiny_config(obstacle_encoder="set")
    message = str(bad.value)
    assert "obstacle_encoder='set'" in message and "('flat', 'tokens')" in message and "\n" not in message
    with pytest.raises(ValueError) as grid:
        tiny_config("grid")
    assert str(grid.value).startswith(
        "obstacle_encoder='tokens' needs an obstacle-slot encoding of the 'nearest' family, "
        "got obstacle_encoding='grid'"
    )
    with pytest.raises(ValueError, match="token_dim=10"):
        tiny_config(token_dim=10)
    with pytest.raises(ValueError, match="ENV='MIN_MAX'"):
        tiny_config(normalization_mapping={"STATE": "MIN_MAX", "ENV": "MIN_MAX", "ACTION": "MIN_MAX"})
    for encoding in ("nearest", "nearest+route", "nearest+velocity", "nearest+maproute"):
        assert tiny_config(encoding).obstacle_encoder == "tokens"  # the whole "nearest" family


def test_flat_is_lerobots_model_and_a_config_without_the_field_loads_as_flat(tmp_path):
    cfg = tiny_config(obstacle_encoder="flat")
    torch.manual_seed(0)
    ours = FormationDiffusionPolicy(cfg)
    torch.manual_seed(0)
    stock = DiffusionPolicy(tiny_config(obstacle_encoder="flat"))
    theirs = stock.diffusion.state_dict()
    assert ours.diffusion.state_dict().keys() == theirs.keys()  # no module added
    assert all(torch.equal(t, theirs[k]) for k, t in ours.diffusion.state_dict().items())
    batch = {OBS_STATE: torch.randn(3, N_OBS, 7), OBS_ENV_STATE: scene(6, present=5).view(3, N_OBS, -1)}
    assert torch.equal(
        global_conditioning(ours.diffusion, batch), stock_global_conditioning(ours.diffusion, batch)
    )

    ours.save_pretrained(tmp_path)
    raw = json.loads((tmp_path / "config.json").read_text())
    for name in ("obstacle_encoder", "token_dim", "action_space"):
        del raw[name]  # as a checkpoint written before these fields
    (tmp_path / "config.json").write_text(json.dumps(raw))
    loaded = FormationDiffusionPolicy.from_pretrained(tmp_path).eval()
    assert loaded.config.obstacle_encoder == "flat"
    noise = torch.randn(3, HORIZON, 2, generator=torch.Generator().manual_seed(1))
    ours.eval()
    assert torch.equal(
        loaded.predict_action_chunk(batch, noise=noise), ours.predict_action_chunk(batch, noise=noise)
    )


def test_tiny_tokens_policy_trains_samples_and_reloads(tmp_path):
    torch.manual_seed(0)
    policy = FormationDiffusionPolicy(tiny_config())
    assert policy.diffusion.obstacle_tokens is not None and policy.ema_diffusion.obstacle_tokens is not None
    env = scene(8, present=5).view(4, N_OBS, -1)
    train = {
        OBS_STATE: torch.randn(4, N_OBS, 7),
        OBS_ENV_STATE: env,
        ACTION: torch.rand(4, HORIZON, 2) * 2 - 1,
        "action_is_pad": torch.zeros(4, HORIZON, dtype=torch.bool),
    }
    loss, _ = policy.forward(train)
    loss.backward()
    assert policy.diffusion.obstacle_tokens.obstacle[0].weight.grad.abs().sum() > 0
    assert any(p is policy.diffusion.obstacle_tokens.ego[0].weight for p in policy.get_optim_params())
    policy.update()  # the EMA covers the encoder
    policy.save_pretrained(tmp_path)
    policy = FormationDiffusionPolicy.from_pretrained(tmp_path).eval()
    assert policy.config.obstacle_encoder == "tokens"

    history = {OBS_STATE: train[OBS_STATE], OBS_ENV_STATE: env}
    noise = torch.randn(8, HORIZON, 2, generator=torch.Generator().manual_seed(2))
    chunks = {}
    for backend in ("eager", "lean", "trace"):
        policy.reconfigure(inference_backend=backend)
        chunks[backend] = policy.sample_action_chunks(history, num_candidates=2, noise=noise)
        assert chunks[backend].shape == (4, 2, HORIZON - N_OBS + 1, 2)
        policy.reset()
        actions = [
            policy.select_action({OBS_STATE: torch.randn(4, 7), OBS_ENV_STATE: env[:, 1]}) for _ in range(3)
        ]
        assert torch.isfinite(torch.stack(actions)).all()
    for backend in ("lean", "trace"):
        torch.testing.assert_close(chunks[backend], chunks["eager"], rtol=1e-5, atol=1e-5)


def parse(name: str) -> TrainPipelineConfig:
    with draccus.config_type("json"):
        return draccus.parse(TrainPipelineConfig, CONFIGS / f"{name}.json", args=["--dataset.root=/tmp"])


def test_ablation_configs_differ_in_the_encoder_only():
    route = parse("formation_diffusion_route").policy
    tokens_run = parse("formation_diffusion_tokens")
    tokens, flat = tokens_run.policy, parse("formation_diffusion_flat_velocity").policy
    assert (tokens.obstacle_encoder, flat.obstacle_encoder) == ("tokens", "flat")
    assert tokens.obstacle_encoding == flat.obstacle_encoding == ENCODING
    assert isinstance(tokens_run.env, FormationEnvConfig)
    for field in ("down_dims", "kernel_size", "n_groups", "diffusion_step_embed_dim", "horizon"):
        assert getattr(tokens, field) == getattr(flat, field) == getattr(route, field)
