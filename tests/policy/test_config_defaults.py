"""The policy config's defaults are the shipped default's sampling and safety settings; the config
stays small; library code holds no dated notes; the env observes its policy's encoding unless told
otherwise; an old config.json naming a retired field loads only where the code runs its value; the
safety layer's fields of an earlier version fold into the current ones (a fixed setting at another
value: a warning, never a refusal)."""

from __future__ import annotations

import json
import logging
import re
import shutil
import sys
from dataclasses import fields
from pathlib import Path

import pytest
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

from lerobot_formation.compat.run_checks import (
    FIXED_LAYER_FIELDS,
    LOOKAHEAD_FIELDS,
    RETIRED_FIELDS,
    WORLD_FIELDS,
    ConfigError,
)
from lerobot_formation.core.safety import layer as safety_layer
from lerobot_formation.core.safety.layer import KnownWorld
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
# every field an old config.json may name that the current one does not
GONE = {*RETIRED_FIELDS, *FIXED_LAYER_FIELDS, *WORLD_FIELDS, *LOOKAHEAD_FIELDS}
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
    assert not set(raw) & GONE  # the shipped file names no retired field
    assert {"safety_horizon", "safety_world"} <= set(raw)
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
    assert not set(own) & GONE


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


def test_the_fixed_layer_fields_are_the_layers_constants():
    wired = {
        "cbf_rate": safety_layer.CBF_RATE,
        "safety_follower_margin": safety_layer.FOLLOWER_MARGIN,
        "safety_route_proposal": safety_layer.ROUTE_PROPOSAL,
        "safety_proposal_blend": safety_layer.PROPOSAL_BLEND,
        "safety_coherence": safety_layer.COHERENCE,
    }
    assert {k: v[0] for k, v in FIXED_LAYER_FIELDS.items()} == wired
    assert set(WORLD_FIELDS.values()) == {f.name for f in fields(KnownWorld)}


def _old_layer_config(tmp_path: Path, name: str, **changes) -> Path:
    """The shipped config.json as an earlier version wrote it: the flat world fields, the two
    lookaheads and the fixed settings, then ``changes`` (None: the field left out)."""
    raw = json.loads((SHIPPED / "config.json").read_text())
    for key in ("safety_horizon", "safety_world"):
        raw.pop(key, None)
    raw.update({key: wired for key, (wired, _) in FIXED_LAYER_FIELDS.items()})
    raw.update(dict.fromkeys(LOOKAHEAD_FIELDS, 20))
    raw.update({key: getattr(KnownWorld(), name) for key, name in WORLD_FIELDS.items()})
    raw.update(changes)
    raw = {k: v for k, v in raw.items() if v is not None}
    folder = tmp_path / name
    folder.mkdir()
    (folder / "config.json").write_text(json.dumps(raw))
    return folder


def test_an_old_config_with_the_flat_world_and_lookahead_fields_loads_into_the_new_ones(tmp_path, caplog):
    folder = _old_layer_config(
        tmp_path,
        "flat",
        safety_moving_obstacles=True,
        safety_action_delay=1,
        safety_max_linear_accel=0.5,
        safety_pose_noise=0.02,
        safety_route_lookahead=12,
        safety_halt_lookahead=12,
    )
    with caplog.at_level(logging.WARNING, logger="lerobot_formation"):
        cfg = PreTrainedConfig.from_pretrained(folder)
    assert cfg.safety_world == KnownWorld(
        moving_obstacles=True, action_delay=1, max_linear_accel=0.5, pose_noise=0.02
    )
    assert cfg.safety_horizon == 12 and not caplog.records  # the fixed settings at their wired values
    assert not set(vars(cfg)) & GONE
    # two lookaheads that differ: the route lookahead's value, and one warning naming both
    caplog.clear()
    differ = _old_layer_config(tmp_path, "differ", safety_route_lookahead=20, safety_halt_lookahead=0)
    with caplog.at_level(logging.WARNING, logger="lerobot_formation"):
        assert PreTrainedConfig.from_pretrained(differ).safety_horizon == 20
    (line,) = [r.getMessage() for r in caplog.records]
    assert "safety_route_lookahead=20 and safety_halt_lookahead=0" in line and "\n" not in line


def test_an_old_k1_config_without_the_layers_fields_loads_with_a_warning(tmp_path, caplog):
    """A config.json older than the layer's fields (K = 1, no filter) ran with the values of
    ``FIELDS_BEFORE`` and ``FIXED_LAYER_FIELDS``: it loads (the fixed settings at their wired values,
    one warning line each where it ran another), the horizon 0, nothing known of the world."""
    gone = dict.fromkeys([*FIXED_LAYER_FIELDS, *LOOKAHEAD_FIELDS, *WORLD_FIELDS])
    folder = _old_layer_config(tmp_path, "k1", num_candidates=None, safety_filter=None, **gone)
    with caplog.at_level(logging.WARNING, logger="lerobot_formation"):
        cfg = PreTrainedConfig.from_pretrained(folder)
    assert (cfg.num_candidates, cfg.safety_filter, cfg.safety_horizon) == (1, "none", 0)
    assert cfg.safety_world == KnownWorld()
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == len(FIXED_LAYER_FIELDS)
    assert any("cbf_rate=2.0" in line and "fixed at 4.0" in line for line in lines), lines
    # a field an old file holds at another value: dropped with its warning, not refused
    caplog.clear()
    other = _old_layer_config(tmp_path, "other", safety_coherence=0.5)
    with caplog.at_level(logging.WARNING, logger="lerobot_formation"):
        assert not hasattr(PreTrainedConfig.from_pretrained(other), "safety_coherence")
    (line,) = [r.getMessage() for r in caplog.records]
    assert "safety_coherence=0.5 is not run any more: the layer's setting is now fixed at 1.0" in line


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
