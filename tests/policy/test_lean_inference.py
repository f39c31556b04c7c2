"""The lean inference path of ``formation_diffusion`` (config field ``inference_backend``): same noise,
same chunks as LeRobot's eager sampler; the traced U-Net is rebuilt when the weights change and never
reaches the state_dict. Tiny random policies; no timing."""

import copy
import logging
import pickle

import pytest
import torch
from plugin_helpers import N_ACT, N_OBS, history_batch, obs_batch, sampling_noise, tiny_config
from safetensors import safe_open

from lerobot_formation.compat import lerobot_compat
from lerobot_formation.policy import modeling_formation_diffusion as modeling
from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig
from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy

TOL = dict(rtol=1e-5, atol=1e-5)


def _policy(**overrides) -> FormationDiffusionPolicy:
    torch.manual_seed(0)
    policy = FormationDiffusionPolicy(tiny_config(**overrides)).eval()
    with torch.no_grad():  # a random EMA, so that live and EMA weights differ
        for p in policy.ema_diffusion.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return policy


def _chunks(policy, backend, batch, k, noise):
    policy.reconfigure(inference_backend=backend)
    return policy.sample_action_chunks(batch, k, noise=noise)


def test_backend_field_defaults_to_eager_and_is_checked(tmp_path):
    assert tiny_config().inference_backend == "eager"
    with pytest.raises(ValueError, match="inference_backend must be one of"):
        tiny_config(inference_backend="compiled")
    tiny_config(inference_backend="trace")._save_pretrained(tmp_path)
    assert FormationDiffusionConfig.from_pretrained(tmp_path).inference_backend == "trace"


@pytest.mark.parametrize("backend", ["lean", "trace"])
@pytest.mark.parametrize(("batch_size", "k"), [(1, 1), (1, 5), (3, 2)])
def test_same_noise_same_chunks_as_eager(backend, batch_size, k):
    policy = _policy()
    batch, noise = history_batch(batch_size), sampling_noise(batch_size * k)
    eager = _chunks(policy, "eager", batch, k, noise)
    torch.testing.assert_close(_chunks(policy, backend, batch, k, noise), eager, **TOL)
    torch.testing.assert_close(_chunks(policy, backend, batch, k, noise), eager, **TOL)  # cached


def test_one_trace_serves_every_batch_size():
    policy = _policy(inference_backend="trace")
    for batch_size, k in [(1, 1), (4, 1), (2, 3), (7, 1), (1, 1)]:
        batch, noise = history_batch(batch_size, seed=batch_size), sampling_noise(batch_size * k, seed=k)
        lean = _chunks(policy, "trace", batch, k, noise)
        torch.testing.assert_close(lean, _chunks(policy, "eager", batch, k, noise), **TOL)
    (traced,) = policy._lean.unets.values()
    assert traced.fn is not None and traced.unet is policy.ema_diffusion.unet


def test_eager_standard_path_is_bit_identical_to_lerobot():
    """Backend eager, K = 1: select_action is LeRobot's (EMA) generate_actions, bit for bit."""
    policy = _policy()
    obs, noise = obs_batch(2), sampling_noise(2)
    policy.reset()
    action = policy.select_action(dict(obs), noise=noise)
    stacked = {k: v[:, None].repeat(1, N_OBS, 1) for k, v in obs.items()}
    stock = policy.ema_diffusion.generate_actions(stacked, noise=noise)
    torch.testing.assert_close(action, stock[:, 0], rtol=0, atol=0)
    chunks = _chunks(policy, "eager", stacked, 1, noise)
    torch.testing.assert_close(chunks[:, 0, :N_ACT], stock, rtol=0, atol=0)


@pytest.mark.parametrize("backend", ["lean", "trace"])
@pytest.mark.parametrize("use_ema", [True, False])
def test_select_action_matches_eager(backend, use_ema):
    """lerobot-eval's path: the same actions over two replans, from the same noise."""
    actions = {}
    for b in ("eager", backend):
        torch.manual_seed(0)
        policy = FormationDiffusionPolicy(tiny_config(use_ema=use_ema, inference_backend=b)).eval()
        policy.reset()
        actions[b] = torch.stack(
            [
                policy.select_action(obs_batch(2, seed=step), noise=sampling_noise(2, seed=step))
                for step in range(2 * N_ACT)
            ]
        )
    torch.testing.assert_close(actions[backend], actions["eager"], **TOL)


def test_unseeded_noise_is_drawn_as_lerobot_draws_it():
    policy = _policy()
    batch = history_batch(2)
    chunks = {}
    for backend in ("eager", "trace"):
        policy.reconfigure(inference_backend=backend)
        torch.manual_seed(5)
        chunks[backend] = policy.sample_action_chunks(batch, 2)
    torch.testing.assert_close(chunks["trace"], chunks["eager"], **TOL)


def test_state_dict_and_checkpoint_unchanged_by_the_trace(tmp_path):
    policy = _policy()
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    policy.save_pretrained(tmp_path / "eager")
    _chunks(policy, "trace", history_batch(1), 1, sampling_noise(1))
    assert policy._lean.unets and policy._lean.steps
    after = policy.state_dict()
    assert list(after) == list(before)
    for key, value in before.items():
        assert torch.equal(after[key], value), key
    policy.save_pretrained(tmp_path / "trace")
    keys = {}
    for name in ("eager", "trace"):
        with safe_open(str(tmp_path / name / "model.safetensors"), framework="pt") as f:
            keys[name] = sorted(f.keys())  # noqa: SIM118
    assert keys["trace"] == keys["eager"]
    assert not any("lean" in k or "trace" in k for k in keys["trace"])
    loaded = FormationDiffusionPolicy.from_pretrained(tmp_path / "trace").eval()
    assert loaded.config.inference_backend == "trace"
    batch, noise = history_batch(2), sampling_noise(2)
    torch.testing.assert_close(
        _chunks(loaded, "trace", batch, 1, noise), _chunks(policy, "eager", batch, 1, noise), **TOL
    )


def test_copies_and_pickles_start_without_the_trace():
    policy = _policy()
    batch, noise = history_batch(1), sampling_noise(1)
    eager = _chunks(policy, "eager", batch, 1, noise)
    _chunks(policy, "trace", batch, 1, noise)
    for clone in (copy.deepcopy(policy), pickle.loads(pickle.dumps(policy))):
        assert not clone._lean.unets and not clone._lean.steps
        torch.testing.assert_close(_chunks(clone, "trace", batch, 1, noise), eager, **TOL)
        assert clone._lean.unets[id(clone.ema_diffusion)].unet is clone.ema_diffusion.unet


def test_trace_follows_weight_changes():
    """An EMA update (as lerobot-train's in-training evaluation sees it), a load_state_dict and a
    dtype round trip each invalidate the frozen trace: the chunks follow the new weights."""
    policy = _policy(inference_backend="trace")
    batch, noise = history_batch(2), sampling_noise(2)

    def check():
        lean = _chunks(policy, "trace", batch, 1, noise)
        torch.testing.assert_close(lean, _chunks(policy, "eager", batch, 1, noise), **TOL)
        return lean

    first = check()
    policy.train()
    with torch.no_grad():
        for p in policy.diffusion.parameters():
            p.add_(0.1 * torch.randn_like(p))
    policy.update()
    policy.eval()
    assert not torch.allclose(check(), first)
    other = _policy()
    other.ema_diffusion.load_state_dict(_policy().diffusion.state_dict())
    policy.load_state_dict(other.state_dict())
    check()
    policy.double().float()
    check()


def test_train_mode_uses_the_live_model_without_a_trace():
    policy = _policy(inference_backend="trace").train()
    batch, noise = history_batch(2), sampling_noise(2)
    lean = _chunks(policy, "trace", batch, 1, noise)
    assert not policy._lean.unets
    torch.testing.assert_close(lean, _chunks(policy, "eager", batch, 1, noise), **TOL)
    policy.eval()
    assert not torch.allclose(_chunks(policy, "eager", batch, 1, noise), lean)  # the EMA's


def test_precomputed_ddim_steps_equal_diffusers_and_follow_the_scheduler():
    """Bit-identical to diffusers' DDIMScheduler.step; set_inference_steps (a new scheduler, another
    step count) is picked up."""
    from lerobot_formation.policy.checkpoint import set_inference_steps

    policy = _policy()
    batch, noise = history_batch(3), sampling_noise(3)
    for steps in (None, 2, 7):
        set_inference_steps(policy, steps)
        eager = _chunks(policy, "eager", batch, 1, noise)
        torch.testing.assert_close(_chunks(policy, "lean", batch, 1, noise), eager, rtol=0, atol=0)
        (entry,) = policy._lean.steps.values()
        assert entry[0] is policy.ema_diffusion.noise_scheduler and entry[2] is not None
        assert len(entry[2].timesteps) == policy.ema_diffusion.num_inference_steps


def test_ddpm_keeps_diffusers_steps():
    policy = _policy(noise_scheduler_type="DDPM", num_inference_steps=None, num_train_timesteps=10)
    batch, noise = history_batch(2), sampling_noise(2)
    chunks = {}
    for backend in ("eager", "lean", "trace"):
        torch.manual_seed(3)  # DDPM's variance noise
        chunks[backend] = _chunks(policy, backend, batch, 1, noise)
    assert next(iter(policy._lean.steps.values()))[2] is None
    torch.testing.assert_close(chunks["lean"], chunks["eager"], rtol=0, atol=0)
    torch.testing.assert_close(chunks["trace"], chunks["eager"], **TOL)


def test_a_ddim_that_differs_from_the_precomputed_steps_keeps_diffusers(monkeypatch, caplog):
    from diffusers.schedulers.scheduling_ddim import DDIMScheduler

    stock_step = DDIMScheduler.step

    def other_step(self, model_output, timestep, sample, *args, **kwargs):  # e.g. a future diffusers
        out = stock_step(self, model_output, timestep, sample, *args, **kwargs)
        out.prev_sample = out.prev_sample * 0.5
        return out

    monkeypatch.setattr(DDIMScheduler, "step", other_step)
    policy = _policy()
    batch, noise = history_batch(1), sampling_noise(1)
    with caplog.at_level(logging.WARNING, logger=modeling.__name__):
        lean = _chunks(policy, "lean", batch, 1, noise)
    assert "differs from diffusers' DDIMScheduler.step" in caplog.text
    torch.testing.assert_close(lean, _chunks(policy, "eager", batch, 1, noise), rtol=0, atol=0)


def test_a_failing_trace_falls_back_to_the_eager_unet(monkeypatch, caplog):
    def broken_trace(*args, **kwargs):
        raise RuntimeError("no tracing here")

    monkeypatch.setattr(torch.jit, "trace", broken_trace)
    policy = _policy()
    batch, noise = history_batch(2), sampling_noise(2)
    with caplog.at_level(logging.WARNING, logger=modeling.__name__):
        lean = _chunks(policy, "trace", batch, 1, noise)
        _chunks(policy, "trace", batch, 1, noise)
    assert caplog.text.count("no tracing here") == 1  # tried once per set of weights
    torch.testing.assert_close(lean, _chunks(policy, "eager", batch, 1, noise), rtol=0, atol=0)


def test_untested_lerobot_keeps_the_stock_sampler(monkeypatch, caplog):
    policy = _policy()  # built on the tested LeRobot (building one on another warns about fast reads)
    monkeypatch.setattr(lerobot_compat, "lerobot_version", lambda: "9.0.0")
    monkeypatch.setattr(lerobot_compat, "_warned", set())
    batch, noise = history_batch(2), sampling_noise(2)
    with caplog.at_level(logging.WARNING, logger=lerobot_compat.__name__):
        lean = _chunks(policy, "trace", batch, 1, noise)
        _chunks(policy, "trace", batch, 1, noise)
    assert len(caplog.records) == 1 and "lean inference path" in caplog.records[0].getMessage()
    assert not policy._lean.unets and not policy._lean.steps
    torch.testing.assert_close(lean, _chunks(policy, "eager", batch, 1, noise), rtol=0, atol=0)


@pytest.mark.parametrize("backend", ["lean", "trace"])
@pytest.mark.parametrize("steps", [1, 4])
def test_sample_prediction_same_chunks_as_eager(backend, steps):
    """A policy that predicts x_0 (prediction_type "sample"): the precomputed DDIM steps handle it
    (not diffusers' fallback) and give LeRobot's eager chunks."""
    policy = _policy(prediction_type="sample", num_inference_steps=steps)
    batch, noise = history_batch(2), sampling_noise(2 * 3)
    eager = _chunks(policy, "eager", batch, 3, noise)
    torch.testing.assert_close(_chunks(policy, backend, batch, 3, noise), eager, **TOL)
    (entry,) = policy._lean.steps.values()
    assert entry[2] is not None and entry[2].predicts_sample


def test_cpu_trace_runs_matrix_product_convolutions_for_few_rows_and_onednn_for_many():
    """On a CPU the trace holds two graphs (``policy.unet_inference``): up to ``SMALL_BATCH_ROWS`` rows
    the matrix-product one, above it oneDNN's; both give the eager chunks."""
    policy = _policy(inference_backend="trace")
    for batch_size, k in [(1, 10), (modeling.SMALL_BATCH_ROWS + 1, 1)]:
        batch, noise = history_batch(batch_size), sampling_noise(batch_size * k)
        torch.testing.assert_close(
            _chunks(policy, "trace", batch, k, noise), _chunks(policy, "eager", batch, k, noise), **TOL
        )
    (traced,) = policy._lean.unets.values()
    assert isinstance(traced.fn, modeling._ByRows)
    calls = []
    for name in ("small", "large"):
        graph = getattr(traced.fn, name)
        setattr(traced.fn, name, lambda *args, graph=graph, name=name: calls.append(name) or graph(*args))
    for rows in (1, modeling.SMALL_BATCH_ROWS, modeling.SMALL_BATCH_ROWS + 1):
        batch, noise = history_batch(rows), sampling_noise(rows)
        _chunks(policy, "trace", batch, 1, noise)
    steps = policy.config.num_inference_steps
    assert calls == ["small"] * 2 * steps + ["large"] * steps
