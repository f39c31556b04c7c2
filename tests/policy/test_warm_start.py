"""Warm-started replans (``warm_start_step``): the guess is the unexecuted rest of the last chunk, the
warm rows are SDEdit from it (diffusers' ``add_noise`` at the j-th timestep, then the remaining steps),
the cold rows and j = 0 are plain sampling, and only the first of K candidates is warm."""

import logging

import pytest
import torch
from plugin_helpers import HORIZON, N_OBS, history_batch, sampling_noise, tiny_config

from lerobot_formation.compat.lerobot_compat import global_conditioning
from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy
from lerobot_formation.policy.replanner import warm_start_guess

TOL = dict(rtol=1e-5, atol=1e-5)
T = HORIZON - N_OBS + 1  # a chunk's length, from the current step on


def _policy(**overrides) -> FormationDiffusionPolicy:
    torch.manual_seed(0)
    return FormationDiffusionPolicy(tiny_config(**overrides)).eval()


def _guess(batch_size: int, seed: int = 2) -> torch.Tensor:
    return torch.rand(batch_size, HORIZON, 2, generator=torch.Generator().manual_seed(seed)) * 2 - 1


def test_guess_is_the_unexecuted_rest_shifted_and_padded():
    previous = torch.arange(2 * T * 2, dtype=torch.float32).reshape(2, T, 2)
    guess = warm_start_guess(previous, torch.tensor([8, 3]), N_OBS, HORIZON)
    assert guess.shape == (2, HORIZON, 2)
    # 8 ran: the new window starts one step before the current one, at the previous chunk's index 7
    torch.testing.assert_close(guess[0, : T - 7], previous[0, 7:])
    torch.testing.assert_close(guess[0, T - 7 :], previous[0, -1:].expand(HORIZON - (T - 7), 2))
    # 3 ran (a filter forced an early replan): starts at index 2
    torch.testing.assert_close(guess[1, : T - 2], previous[1, 2:])
    torch.testing.assert_close(guess[1, T - 2 :], previous[1, -1:].expand(HORIZON - (T - 2), 2))


@pytest.mark.parametrize("backend", ["eager", "lean", "trace"])
def test_cold_rows_and_step_zero_are_plain_sampling(backend):
    policy = _policy(inference_backend=backend)
    batch, noise, guess = history_batch(3), sampling_noise(3), _guess(3)
    plain = policy.sample_action_chunks(batch, 1, noise=noise)
    none_warm = (guess, torch.zeros(3, dtype=torch.bool))
    torch.testing.assert_close(
        policy.sample_action_chunks(batch, 1, noise=noise, warm_start=none_warm, warm_start_step=2), plain
    )
    all_warm = (guess, torch.ones(3, dtype=torch.bool))
    torch.testing.assert_close(
        policy.sample_action_chunks(batch, 1, noise=noise, warm_start=all_warm, warm_start_step=0), plain
    )


@pytest.mark.parametrize("backend", ["eager", "lean", "trace"])
@pytest.mark.parametrize("j", [1, 3])
def test_warm_rows_are_sdedit_from_their_guess(backend, j):
    """Rows 0 and 2 warm, row 1 cold, in one call: the warm rows equal a hand-written SDEdit with
    diffusers' own scheduler (noise the guess to t_j, then step down from there), the cold row equals
    plain sampling."""
    policy = _policy(inference_backend=backend, warm_start_step=j)
    batch, noise, guess = history_batch(3), sampling_noise(3), _guess(3)
    use = torch.tensor([True, False, True])
    got = policy.sample_action_chunks(batch, 1, noise=noise, warm_start=(guess, use))[:, 0]
    model = policy.inference_model
    scheduler = model.noise_scheduler
    scheduler.set_timesteps(policy.config.num_inference_steps)
    ts = scheduler.timesteps
    with torch.inference_mode():
        cond = global_conditioning(model, batch)
        x = scheduler.add_noise(guess, noise, torch.full((3,), int(ts[j])))
        for t in ts[j:]:
            eps = model.unet(x, torch.full((3,), int(t)), cond)
            x = scheduler.step(eps, t, x).prev_sample
    want = x[:, N_OBS - 1 :]
    torch.testing.assert_close(got[0], want[0], **TOL)
    torch.testing.assert_close(got[2], want[2], **TOL)
    plain = policy.sample_action_chunks(batch, 1, noise=noise, warm_start_step=0)[:, 0]
    torch.testing.assert_close(got[1], plain[1], **TOL)
    assert not torch.allclose(got[0], plain[0], **TOL)  # the guess did change the warm rows


def test_only_the_first_candidate_continues_the_last_plan():
    policy = _policy(inference_backend="lean", warm_start_step=2)
    B, K = 2, 3
    batch, noise, guess = history_batch(B), sampling_noise(B * K), _guess(B)
    warm = policy.sample_action_chunks(
        batch, K, noise=noise, warm_start=(guess, torch.ones(B, dtype=torch.bool))
    )
    cold = policy.sample_action_chunks(batch, K, noise=noise, warm_start_step=0)
    torch.testing.assert_close(warm[:, 1:], cold[:, 1:], **TOL)
    assert not torch.allclose(warm[:, 0], cold[:, 0], **TOL)


def test_all_candidates_warm_on_request():
    policy = _policy(inference_backend="lean", warm_start_step=2)
    B, K = 2, 3
    batch, noise, guess = history_batch(B), sampling_noise(B * K), _guess(B)
    use = torch.tensor([True, False])
    warm = policy.sample_action_chunks(batch, K, noise=noise, warm_start=(guess, use), warm_all=True)
    # each candidate of row 0 equals one warm-started sample of its own noise, row 1 stays cold
    for k in range(K):
        one = policy.sample_action_chunks(
            {key: v[:1] for key, v in batch.items()},
            1,
            noise=noise[k : k + 1],
            warm_start=(guess[:1], use[:1]),
        )
        torch.testing.assert_close(warm[0, k], one[0, 0], **TOL)
    cold = policy.sample_action_chunks(batch, K, noise=noise, warm_start_step=0)
    torch.testing.assert_close(warm[1], cold[1], **TOL)


def test_warm_start_step_is_checked_with_its_value(caplog):
    with pytest.raises(
        ValueError, match=r"warm_start_step must be in \[0, 4\) \(num_inference_steps 4\), got 4"
    ):
        tiny_config(warm_start_step=4)
    with pytest.raises(ValueError, match=r"got -1"):
        tiny_config(warm_start_step=-1)
    cfg = tiny_config(warm_start_step=1)
    assert cfg.plans_per_episode and not cfg.safety_layer
    # the engine's step override turns a warm start it leaves no room for off, and says so
    from lerobot_formation.policy.checkpoint import set_inference_steps

    policy = _policy(warm_start_step=3)
    with caplog.at_level(logging.WARNING):
        set_inference_steps(policy, 3)
    assert policy.config.warm_start_step == 0 and "warm_start_step 3 needs more than 3" in caplog.text
    policy.sample_action_chunks(history_batch(1), 1, warm_start=(_guess(1), torch.ones(1, dtype=torch.bool)))
    # a warm start past the sampler's steps is refused when sampling
    with pytest.raises(ValueError, match="warm_start_step must be below the sampler's 3 steps, got 5"):
        policy.sample_action_chunks(
            history_batch(1), 1, warm_start=(_guess(1), torch.ones(1, dtype=torch.bool)), warm_start_step=5
        )
