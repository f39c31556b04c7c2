"""With every realistic condition off, trajectories, observations and dataset bytes are exactly those
of the code before the conditions existed: ``tests/fixtures/conditions_off_reference.npz`` and
``conditions_off_dataset_sha256.json`` were recorded at commit d6ba45a
(``tests/fixtures/make_conditions_off_reference.py``)."""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"


def test_trajectories_and_observations_unchanged():
    sys.path.insert(0, str(FIXTURES))
    try:
        from make_conditions_off_reference import reference
    finally:
        sys.path.remove(str(FIXTURES))
    want = np.load(FIXTURES / "conditions_off_reference.npz")
    got = reference()
    assert sorted(got) == sorted(want.files)
    # On a CPU whose numpy SIMD sin/cos round the last bit like the recording machine's, every array is
    # equal bit for bit. On another (AVX-512 against AVX2) the leaders' poses differ by ~1e-15, and the
    # paper's follower law (sign(), eq. fol1) turns that into a different chattering of the followers
    # (up to 0.14 m): there the floats must agree to 1e-12 and, of the agents, the leaders only.
    exact = np.array_equal(got["pac_poses"], want["pac_poses"])
    for key in want.files:
        g, w = got[key], want[key]
        if not exact and key == "pac_agent_clearance":
            continue  # the followers' clearance included
        if not exact and key == "pac_positions":
            g, w = g[..., :2, :], w[..., :2, :]
        if exact or w.dtype.kind != "f":
            np.testing.assert_array_equal(g, w, err_msg=key)
        else:
            np.testing.assert_allclose(g, w, rtol=0, atol=1e-12, err_msg=key)


def test_conditions_all_off_is_no_conditions():
    from lerobot_formation.core.controllers.pac import PACController
    from lerobot_formation.core.episodes.rollout import Teams, rollout
    from lerobot_formation.core.perception.conditions import Conditions
    from lerobot_formation.core.world.sampling import sample_scenes

    scenes = sample_scenes([1_000_000, 1_000_001])
    assert Teams(scenes, conditions=Conditions()).world is None
    a = rollout(scenes, PACController(), max_steps=80)
    b = rollout(scenes, PACController(), max_steps=80, conditions=Conditions())
    np.testing.assert_array_equal(a.poses, b.poses)
    assert b.obstacle_paths is None and b.seen_step is None


@pytest.mark.parametrize("cli", [False, True])
def test_dataset_bytes_unchanged(tmp_path, cli):
    """Two episodes of the generator (no condition flag, or every flag at its default value)."""
    from datasets_scripts import generate_pac_dataset

    root = tmp_path / "ds"
    argv = ["--episodes", "2", "--root", str(root), "--repo-id", "local/formation_ref", "--workers", "0"]
    argv += ["--obstacle-encoding", "nearest+route", "--no-progress"]
    if cli:
        argv += ["--env.obstacle_noise", "0", "--env.action_delay", "0", "--env.obstacle_memory", "true"]
    assert generate_pac_dataset.main(argv) == 0
    want = json.loads((FIXTURES / "conditions_off_dataset_sha256.json").read_text())
    data = root / "data" / "chunk-000" / "file-000.parquet"
    assert hashlib.sha256(data.read_bytes()).hexdigest() == want["nearest+route, 2 episodes, seed 0"]
