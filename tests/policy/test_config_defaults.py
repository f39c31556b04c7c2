"""The policy config's defaults are the shipped default's sampling and safety settings; the config
stays small; library code holds no dated notes; the env observes its policy's encoding unless told
otherwise; an old config.json naming a retired field loads only where the code runs its value."""

from __future__ import annotations

import json
import re
import shutil
import sys
from dataclasses import fields
from pathlib import Path

import pytest
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

from lerobot_formation.compat.run_checks import RETIRED_FIELDS, ConfigError
from lerobot_formation.envs.env_config import FormationEnvConfig
from lerobot_formation.policy.configuration_formation_diffusion import LAYER_OFF, FormationDiffusionConfig

REPO = Path(__file__).resolve().parents[2]
SHIPPED = REPO / "pretrained" / "formation_diffusion_route_v1"
# Own fields that are the network's or the training's (they may stay the paper's), not sampling or safety
ARCHITECTURE_AND_TRAINING = {
    "egocentric_obstacles",
    "max_obstacles",
    "obstacle_encoder",
    "token_dim",
    "action_space",
    "use_ema",
    "ema_power",
}
# LeRobot's fields that decide how a chunk is sampled
LEROBOT_SAMPLING = ("noise_scheduler_type", "num_inference_steps")
MAX_OWN_FIELDS = 30
DATED = re.compile(r"20[0-9]{2}-[0-9]{2}-[0-9]{2}|before 2026|night|evening|morning")


def own_fields() -> list[str]:
    base = {f.name for f in fields(DiffusionConfig)}
    return [f.name for f in fields(FormationDiffusionConfig) if f.name not in base]


def sampling_and_safety() -> list[str]:
    return [n for n in own_fields() if n not in ARCHITECTURE_AND_TRAINING] + list(LEROBOT_SAMPLING)


def test_the_defaults_are_the_shipped_defaults_sampling_and_safety_settings():
    default = FormationDiffusionConfig()
    shipped = PreTrainedConfig.from_pretrained(SHIPPED)
    differ = {
        n: (getattr(default, n), getattr(shipped, n))
        for n in sampling_and_safety()
        if getattr(default, n) != getattr(shipped, n)
    }
    assert not differ, differ
    # the headline configuration: the shipped weights with their layer on
    assert (default.num_candidates, default.safety_filter) == (10, "cbf") and default.safety_layer
    assert (shipped.num_candidates, shipped.safety_filter) == (10, "cbf")
    raw = json.loads((SHIPPED / "config.json").read_text())
    assert not set(raw) & set(RETIRED_FIELDS)  # the shipped file names no retired field
    # the network and training stay the paper's
    assert (tuple(default.down_dims), default.horizon, default.n_action_steps) == ((256, 512, 1024), 64, 10)


def test_the_standard_policy_is_the_layer_off():
    cfg = FormationDiffusionConfig(**LAYER_OFF)
    assert not cfg.safety_layer
    # a paper-style encoding needs the layer off, and the error says how
    with pytest.raises(ConfigError, match="--policy.num_candidates=1 --policy.safety_filter=none"):
        FormationDiffusionConfig(obstacle_encoding="grid")
    FormationDiffusionConfig(obstacle_encoding="grid", fixed_action_bounds=False, **LAYER_OFF)


def test_the_policy_config_keeps_at_most_30_fields_of_its_own():
    own = own_fields()
    assert len(own) <= MAX_OWN_FIELDS, (len(own), own)
    assert not set(own) & set(RETIRED_FIELDS)


def test_no_dated_note_in_library_code():
    hits = []
    for path in sorted((REPO / "lerobot_formation").rglob("*")):
        if not path.is_file() or path.suffix not in (".py", ".md", ".txt", ".json", ".toml", ".cfg"):
            continue
        for i, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if DATED.search(line):
                hits.append(f"{path.relative_to(REPO)}:{i}: {line.strip()}")
    assert not hits, "dated notes belong in docs/log.md:\n" + "\n".join(hits)


def _eval_config(monkeypatch, *args: str):
    import draccus
    from lerobot.configs.eval import EvalPipelineConfig

    args = ["--env.type=formation", *args]
    # LeRobot reads --policy.path from sys.argv and parses the rest (its parser.wrap drops the path)
    monkeypatch.setattr(sys, "argv", ["lerobot-eval", f"--policy.path={SHIPPED}", *args])
    return draccus.parse(EvalPipelineConfig, args=args)


def test_lerobot_eval_of_the_shipped_path_runs_the_headline_configuration(monkeypatch):
    cfg = _eval_config(monkeypatch)
    assert (cfg.policy.num_candidates, cfg.policy.safety_filter) == (10, "cbf")
    assert cfg.env.obstacle_encoding == "nearest+route" == cfg.policy.obstacle_encoding
    assert cfg.env.features["environment_state"].shape == (55,)
    assert cfg.env.gym_kwargs["obstacle_encoding"] == "nearest+route"
    # the same encoding given is fine; another is an error naming both
    assert _eval_config(monkeypatch, "--env.obstacle_encoding=nearest+route").env.encoding == "nearest+route"
    with pytest.raises(Exception) as e:
        _eval_config(monkeypatch, "--env.obstacle_encoding=grid")
    message = str(e.value) + str(e.value.__cause__) + str(e.value.__context__)
    assert "--env.obstacle_encoding=grid differs from the policy's obstacle_encoding=nearest+route" in message


def test_an_env_config_without_a_policy_observes_the_gym_envs_default():
    env = FormationEnvConfig()
    assert env.obstacle_encoding is None and env.encoding == "grid"
    assert env.features["environment_state"].shape == (51,)
    assert env.gym_kwargs["obstacle_encoding"] == "grid"
    env.take_policy_encoding(FormationDiffusionConfig())  # what the pipelines hand over
    assert env.obstacle_encoding == "nearest+route" and env.features["environment_state"].shape == (55,)
    given = FormationEnvConfig(obstacle_encoding="nearest")
    with pytest.raises(ConfigError) as e:
        given.take_policy_encoding(FormationDiffusionConfig())
    assert "--env.obstacle_encoding=nearest differs from the policy's obstacle_encoding=nearest+route" in str(
        e.value
    )


def _old_checkpoint(tmp_path: Path, **changes) -> Path:
    folder = tmp_path / "old"
    folder.mkdir()
    raw = json.loads((SHIPPED / "config.json").read_text())
    raw.update(changes)
    (folder / "config.json").write_text(json.dumps(raw))
    return folder


def test_an_old_config_naming_a_retired_field_loads_only_at_the_value_the_code_runs(tmp_path):
    same = _old_checkpoint(tmp_path, safety_recheck=True, timestep_spacing="leading", action_high=[0.6, 1.5])
    cfg = PreTrainedConfig.from_pretrained(same)
    assert cfg.num_candidates == 10 and not hasattr(cfg, "safety_recheck")
    shutil.rmtree(same)
    other = _old_checkpoint(tmp_path, safety_fallback_lookahead=30)
    with pytest.raises(ConfigError) as e:
        PreTrainedConfig.from_pretrained(other)
    line = str(e.value)
    assert "\n" not in line
    assert (
        "retired field safety_fallback_lookahead=30 differs from the value the policy now runs with (0)"
        in line
    )
    assert json.loads((other / "config.json").read_text())["safety_fallback_lookahead"] == 30  # untouched


def test_an_old_config_without_the_layers_fields_keeps_the_policy_it_was(tmp_path):
    """A config.json written before a field existed ran without it: it does not get the new default."""
    raw = json.loads((SHIPPED / "config.json").read_text())
    for name in ("num_candidates", "safety_filter", "sampling_guidance", "chunk_smoothing"):
        del raw[name]
    folder = tmp_path / "older"
    folder.mkdir()
    (folder / "config.json").write_text(json.dumps(raw))
    cfg = PreTrainedConfig.from_pretrained(folder)
    assert (cfg.num_candidates, cfg.safety_filter, cfg.sampling_guidance, cfg.chunk_smoothing) == (
        1,
        "none",
        0,
        0,
    )


def test_the_bench_controllers_keep_their_names_meaning():
    from lerobot_formation.bench.controllers import make_controller
    from lerobot_formation.bench.settings import ControllerOptions
    from lerobot_formation.core.world.dynamics import FormationParams
    from lerobot_formation.policy.checkpoint import load_policy

    bundle = load_policy(SHIPPED)
    options = ControllerOptions(policy_path=str(SHIPPED), candidates=5)
    got = {
        name: make_controller(name, FormationParams(), options, bundle).config
        for name in ("diffusion", "diffusion-safe", "diffusion-policy")
    }
    assert (got["diffusion"].num_candidates, got["diffusion"].safety_filter) == (1, "none")
    assert got["diffusion"].sampling_guidance == 0.0
    assert (got["diffusion-safe"].num_candidates, got["diffusion-safe"].safety_filter) == (5, "cbf")
    assert (got["diffusion-policy"].num_candidates, got["diffusion-policy"].safety_filter) == (10, "cbf")
