"""A resumed run that has already reached its --steps says why it trains 0 steps (issue 27)."""

from __future__ import annotations

import logging
from types import SimpleNamespace

from lerobot_formation.envs.env_config import FormationEnvConfig
from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig


def make_env_pre_post_processors(env_cfg, policy_cfg):  # noqa: ARG001  (LeRobot's name and signature)
    return env_cfg.get_env_processors()


def train(cfg, step):  # LeRobot's train(): its cfg and step are locals when it builds the env processors
    return make_env_pre_post_processors(cfg.env, cfg.policy)


def _cfg(resume: bool, steps: int):
    policy = FormationDiffusionConfig(device="cpu", push_to_hub=False)
    return SimpleNamespace(
        resume=resume,
        steps=steps,
        checkpoint_path="outputs/x/checkpoints/last",
        env=FormationEnvConfig(),
        policy=policy,
    )


def test_a_finished_run_resumed_says_why_nothing_is_trained(caplog):
    with caplog.at_level(logging.WARNING, logger="lerobot_formation"):
        train(_cfg(resume=True, steps=10), step=10)
    (line,) = [r.getMessage() for r in caplog.records if r.name == "lerobot_formation"]
    assert "at step 10" in line and "--steps is 10" in line and "0 steps" in line and "N > 10" in line


def test_a_run_with_steps_left_or_a_fresh_run_says_nothing(caplog):
    with caplog.at_level(logging.WARNING, logger="lerobot_formation"):
        train(_cfg(resume=True, steps=12), step=10)
        train(_cfg(resume=False, steps=10), step=0)
    assert not [r for r in caplog.records if r.name == "lerobot_formation"]
