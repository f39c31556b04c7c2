"""Each episode of a diffusion controller draws its sampler's noise from its own stream and is sampled
in a denoiser call of its own (issue 61, item 7): the noise of an episode's k-th replan is the same run
alone, in a batch of three and in another order, it is the noise the sampler gets, and the episode's
actions are the same bit for bit."""

import numpy as np
import pytest
import torch
from helpers import tiny_diffusion_kwargs

from lerobot_formation.bench.diffusion_controller import DiffusionController, episode_noise_seeds
from lerobot_formation.bench.evaluation import evaluate
from lerobot_formation.core.episodes.levels import TUNING_SEED_START
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.core.world.sampling import sample_scenes

K, STEPS = 3, 40


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    """A tiny untrained 'nearest+route' policy (an encoding of the safety layer, the route proposal's
    too) and its processors."""
    from lerobot.utils.constants import ACTION, OBS_STATE

    from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig
    from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy
    from lerobot_formation.policy.processor_formation_diffusion import (
        make_formation_diffusion_pre_post_processors,
    )

    torch.manual_seed(0)
    cfg = FormationDiffusionConfig(
        **tiny_diffusion_kwargs(env_dim=55),
        obstacle_encoding="nearest+route",
        fixed_action_bounds=True,
        noise_scheduler_type="DDIM",
        num_inference_steps=2,
    )
    stats = {OBS_STATE: {"min": torch.full((7,), -5.0), "max": torch.full((7,), 5.0)}}
    stats[ACTION] = {"min": torch.zeros(2), "max": torch.ones(2)}  # replaced by the fixed bounds
    policy = FormationDiffusionPolicy(cfg)
    pre, post = make_formation_diffusion_pre_post_processors(cfg, stats)
    return policy, pre, post


def noise_per_episode(bundle, scenes, seed=3, name="diffusion-safe", actions=None) -> dict[int, list]:
    """Run best-of-K with the CBF filter (replans cut short, so episodes replan at different steps) on
    ``scenes`` in one batch; each scene's (by seed) initial noise (K, horizon, 2) of each replan. With
    a dict ``actions``, each scene's executed actions (steps, 2) go into it."""
    ctrl = DiffusionController(
        None,
        seed=seed,
        policy_bundle=bundle,
        overrides={"num_candidates": K, "safety_filter": "cbf"},
        name=name,
    )
    drawn, sampled = [], []
    draw, sample = ctrl._noise, ctrl.policy.sample_action_chunks

    def recording_draw(rows, per_row):
        out = draw(rows, per_row)
        drawn.append((rows.tolist(), out))
        return out

    def recording_sample(batch, num_candidates=1, noise=None, **kw):
        sampled.append(noise)
        return sample(batch, num_candidates, noise=noise, **kw)

    ctrl._noise = recording_draw
    ctrl.policy.sample_action_chunks = recording_sample
    try:
        rec = evaluate(ctrl, scenes, FormationParams(max_steps=STEPS))
    finally:
        del ctrl.policy.sample_action_chunks  # the shared policy's own method again
    # one sampler call per replanning episode (K rows), with that episode's draws
    assert all(len(s) == K for s in sampled), "a sampler call ran more than one episode"
    assert torch.equal(torch.cat(sampled), torch.cat([d for _, d in drawn])), "the sampler got other noise"
    if actions is not None:
        actions.update({int(s): rec.episode(b)["actions"] for b, s in enumerate(scenes.seeds)})
    out: dict[int, list[torch.Tensor]] = {int(s): [] for s in scenes.seeds}
    for rows, noise in drawn:
        for j, row in enumerate(rows):
            out[int(scenes.seeds[row])].append(noise[j * K : (j + 1) * K])
    return out


def test_an_episode_draws_the_same_noise_alone_in_a_batch_and_in_another_order(bundle):
    scenes = sample_scenes(TUNING_SEED_START + np.arange(3))
    alone, acts = {}, [{}, {}, {}]
    for b in range(3):
        alone.update(noise_per_episode(bundle, scenes[[b]], actions=acts[0]))
    batched = noise_per_episode(bundle, scenes, actions=acts[1])
    reordered = noise_per_episode(bundle, scenes[[2, 0, 1]], actions=acts[2])
    for seed, draws in alone.items():
        for other in acts[1:]:  # the denoiser ran each episode by itself: no batch rounding either
            np.testing.assert_array_equal(other[seed], acts[0][seed], err_msg=f"scene {seed}")
        assert len(draws) >= 3, f"scene {seed}: {len(draws)} replans"
        for other in (batched, reordered):
            assert len(other[seed]) == len(draws), f"scene {seed}: other replans in a batch"
            for k, (a, b) in enumerate(zip(draws, other[seed], strict=True)):
                assert torch.equal(a, b), f"scene {seed}: replan {k} drew other noise in a batch"
    firsts = [draws[0] for draws in alone.values()]
    assert not torch.equal(firsts[0], firsts[1]) and not torch.equal(firsts[1], firsts[2])
    # the run's seed and the controller's name are part of the stream
    seed = int(scenes.seeds[0])
    assert not torch.equal(noise_per_episode(bundle, scenes[[0]], seed=4)[seed][0], alone[seed][0])
    assert not torch.equal(noise_per_episode(bundle, scenes[[0]], name="other")[seed][0], alone[seed][0])


def test_episode_noise_seeds_tell_scenes_apart_by_seed_and_goal():
    goals = np.array([[1.0, 5.0], [1.0, 5.0], [1.0, 5.5], [1.0, 5.0]])
    seeds = episode_noise_seeds(0, "diffusion", [-1, -1, -1, 7], goals)
    assert seeds[0] == seeds[1]  # the same scene: the same stream
    assert len({seeds[0], seeds[2], seeds[3]}) == 3  # another goal or scene seed: another stream
    assert seeds == episode_noise_seeds(0, "diffusion", np.array([-1, -1, -1, 7]), goals)  # repeatable
    assert all(0 <= s < 2**64 for s in seeds)
