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


def test_set_with_an_unknown_field_is_refused_and_writes_nothing(tmp_path):
    ckpt = save_nearest_checkpoint(tmp_path / "ckpt")
    with pytest.raises(SystemExit, match="expected FIELD=VALUE with a formation_diffusion config field"):
        _derive(str(ckpt), str(tmp_path / "new"), "--set", "no_such_field=1")
    assert not (tmp_path / "new").exists()
