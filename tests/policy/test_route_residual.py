"""``action_space="route-residual"``: the network denoises a correction to route pursuit's chunk. The
prior is route pursuit's own chunk, the loss sees the residual, every sampler adds the prior back,
and a config that cannot build it is refused naming the field and the value."""

import numpy as np
import pytest
import torch
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE
from test_obstacle_tokens import ENCODING, HORIZON, N_OBS, tiny_config

from lerobot_formation.core.controllers.route_pursuit import pursuit_chunk
from lerobot_formation.core.encodings.obstacle_grid import get_encoding
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy


def observation(B: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """Observation histories (B, N_OBS, ...) with a route hint ahead of the team and a goal beyond it."""
    g = torch.Generator().manual_seed(seed)
    encoding = get_encoding(ENCODING)
    env = torch.zeros(B, N_OBS, encoding.dim())
    at = encoding.dim() - encoding.trailing
    env[..., 0:2] = torch.tensor([1.0, 4.0]) + torch.rand(B, 1, 2, generator=g)  # goal, body frame
    env[..., at : at + 4] = torch.tensor([0.3, 1.0, 0.8, 2.0]) * (0.5 + torch.rand(B, 1, 4, generator=g))
    return {OBS_STATE: torch.randn(B, N_OBS, 7, generator=g), OBS_ENV_STATE: env}


def pair(**overrides) -> tuple[FormationDiffusionPolicy, FormationDiffusionPolicy]:
    """A residual policy and a velocity policy with the same weights."""
    torch.manual_seed(0)
    residual = FormationDiffusionPolicy(tiny_config(action_space="route-residual", **overrides))
    velocity = FormationDiffusionPolicy(tiny_config(**overrides))
    velocity.load_state_dict(residual.state_dict())
    return residual.eval(), velocity.eval()


def test_the_prior_is_route_pursuits_chunk_in_normalised_units():
    policy, _ = pair()
    batch = observation(3)
    prior = policy.diffusion.route_prior(batch)
    assert prior.shape == (3, HORIZON, 2)
    route, goal = get_encoding(ENCODING).route_hint(batch[OBS_ENV_STATE][:, -1].numpy())
    cfg = policy.config
    chunk = pursuit_chunk(route, goal, HORIZON - N_OBS + 1, FormationParams().dt, cfg.action_high[1])
    low, high = np.array(cfg.action_low), np.array(cfg.action_high)
    physical = (prior.numpy() + 1.0) / 2.0 * (high - low) + low
    np.testing.assert_allclose(physical[:, N_OBS - 1 :], chunk, atol=1e-5)
    np.testing.assert_allclose(physical[:, 0], chunk[:, 0], atol=1e-5)  # the past step: its first command
    assert (chunk[..., 0] > 0).all()  # it drives toward the carrot


def test_the_loss_is_on_the_residual():
    policy, velocity = pair()
    batch = observation(4)
    prior = policy.diffusion.route_prior(batch)
    pad = torch.zeros(4, HORIZON, dtype=torch.bool)
    action = (prior + 0.2 * torch.rand(4, HORIZON, 2)).clamp(-1, 1)
    torch.manual_seed(3)
    ours = policy.diffusion.compute_loss({**batch, ACTION: action, "action_is_pad": pad})
    torch.manual_seed(3)
    theirs = velocity.diffusion.compute_loss({**batch, ACTION: (action - prior) / 2, "action_is_pad": pad})
    assert torch.equal(ours, theirs)


@pytest.mark.parametrize("backend", ["eager", "lean", "trace"])
def test_every_sampler_adds_the_prior_back(backend):
    policy, velocity = pair(inference_backend=backend)
    batch = observation(3, seed=1)
    prior = policy.diffusion.route_prior(batch)
    noise = torch.randn(3, HORIZON, 2, generator=torch.Generator().manual_seed(2))
    chunk = policy.predict_action_chunk(batch, noise=noise)
    sample = velocity.predict_action_chunk(batch, noise=noise)
    start = N_OBS - 1
    want = (prior[:, start : start + policy.config.n_action_steps] + 2 * sample).clamp(-1, 1)
    torch.testing.assert_close(chunk, want, rtol=0, atol=1e-5)
    # the batched sampler of the safety layer and the engine: K candidates, each with the prior
    K = 2
    noise = torch.randn(3 * K, HORIZON, 2, generator=torch.Generator().manual_seed(4))
    chunks = policy.sample_action_chunks(batch, num_candidates=K, noise=noise)
    samples = velocity.sample_action_chunks(batch, num_candidates=K, noise=noise)
    want = (prior[:, None, start:] + 2 * samples).clamp(-1, 1)
    torch.testing.assert_close(chunks, want, rtol=0, atol=1e-5)


@pytest.mark.parametrize(
    ("overrides", "names"),
    [
        ({"action_space": "waypoints"}, "action_space='waypoints'"),
        ({"obstacle_encoding": "nearest", "obstacle_encoder": "flat"}, "obstacle_encoding='nearest'"),
        ({"fixed_action_bounds": False}, "fixed_action_bounds=false"),
    ],
)
def test_a_config_that_cannot_build_it_is_refused_naming_the_field(overrides, names):
    encoding = overrides.pop("obstacle_encoding", ENCODING)
    with pytest.raises(ValueError) as bad:
        tiny_config(encoding, **{"action_space": "route-residual", **overrides})
    assert names in str(bad.value) and "\n" not in str(bad.value)
