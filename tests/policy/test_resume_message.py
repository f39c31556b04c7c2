"""A resumed run that has already reached its --steps says why it trains 0 steps (issue 27).

``lerobot-train --config_path=CKPT/pretrained_model/train_config.json --resume=true`` validates its
config first; that is where the message comes from, with the step LeRobot is about to resume from
(``CKPT/training_state/training_step.json``).
"""

from __future__ import annotations

import json
import logging
import sys

from lerobot.configs.default import DatasetConfig
from lerobot.configs.train import TrainPipelineConfig

from lerobot_formation.envs.env_config import FormationEnvConfig
from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig


def _validate(tmp_path, monkeypatch, resume: bool, steps: int, checkpoint_step: int) -> str:
    """Validate a training config as ``lerobot-train`` does; the checkpoint folder it resumes from."""
    checkpoint = tmp_path / "run" / "checkpoints" / "last"
    (checkpoint / "pretrained_model").mkdir(parents=True, exist_ok=True)
    (checkpoint / "pretrained_model" / "train_config.json").write_text("{}")  # only its path is read here
    (checkpoint / "training_state").mkdir(exist_ok=True)
    (checkpoint / "training_state" / "training_step.json").write_text(json.dumps({"step": checkpoint_step}))
    argv = ["lerobot-train", f"--config_path={checkpoint / 'pretrained_model' / 'train_config.json'}"]
    monkeypatch.setattr(sys, "argv", argv)  # LeRobot's validate reads --config_path from the command line
    cfg = TrainPipelineConfig(
        dataset=DatasetConfig(repo_id="local/x", root=str(tmp_path)),
        env=FormationEnvConfig(),
        policy=FormationDiffusionConfig(device="cpu", push_to_hub=False),
        resume=resume,
        steps=steps,
    )
    cfg.validate()
    return str(checkpoint)


def test_a_finished_run_resumed_says_why_nothing_is_trained(tmp_path, monkeypatch, caplog):
    with caplog.at_level(logging.WARNING, logger="lerobot_formation"):
        checkpoint = _validate(tmp_path, monkeypatch, resume=True, steps=10, checkpoint_step=10)
    (line,) = [r.getMessage() for r in caplog.records if r.name == "lerobot_formation"]
    assert line == (
        f"resume: the checkpoint {checkpoint} is at step 10 and the run's --steps is 10, so there is nothing "
        "to train (0 steps); pass --steps=N with N > 10 to train on"
    )


def test_a_run_with_steps_left_or_a_fresh_run_says_nothing(tmp_path, monkeypatch, caplog):
    with caplog.at_level(logging.WARNING, logger="lerobot_formation"):
        _validate(tmp_path, monkeypatch, resume=True, steps=12, checkpoint_step=10)
        _validate(tmp_path, monkeypatch, resume=False, steps=10, checkpoint_step=10)
    assert not [r for r in caplog.records if r.name == "lerobot_formation"]
