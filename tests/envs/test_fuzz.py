"""Seeded-random fuzzing (hypothesis is not a dependency): malformed scene files always give a
ValueError, never another exception; random actions either give a ValueError or are clipped, and the
env stays usable."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest

from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.core.world.scene_files import load_scenes
from lerobot_formation.core.world.scenes import Scenes
from lerobot_formation.envs.env import FormationEnv
from lerobot_formation.envs.vector_env import FormationVectorEnv

BASE = {
    "scenes": [
        {"obstacles": [[3.0, 3.0, 0.5], [2.0, 4.5, 0.4]], "goal": [5.0, 5.0], "start": [0.0, 0.0, 1.5707963]},
        {"obstacles": [[4.0, 1.5, 0.6]], "goal": [5.0, 5.0]},
    ]
}
JUNK = [
    None, True, False, "", "3", "nan", 0, -1, 3, 0.5, -0.0, 2**63, 10**400, 1e308, -1e308,
    float("nan"), float("inf"), -float("inf"), [], [[]], [None], [1, 2], [1, 2, 3, 4], [[1, 2, 3]],
    {}, {"x": 1}, {"scenes": []}, [True, False], ["a", "b", "c"], 1e-320, 60.0, -60.0, 1e5,
]  # fmt: skip


def _mutate(rng: np.random.Generator, data):
    """One random edit somewhere in the nested structure: replace, delete or add."""
    data = copy.deepcopy(data)
    junk = copy.deepcopy(JUNK[rng.integers(len(JUNK))])
    containers = []

    def walk(node, parent, key):
        containers.append((node, parent, key))
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, node, k)
        elif isinstance(node, list):
            for i, v in enumerate(node):
                walk(v, node, i)

    walk(data, None, None)
    node, parent, key = containers[rng.integers(len(containers))]
    op = rng.integers(4)
    if parent is None:
        return junk if op == 0 else data
    if op == 0 or op == 1:  # replace the value (twice as likely)
        parent[key] = junk
    elif op == 2:  # delete it
        del parent[key]
    elif isinstance(parent, dict):  # add an unknown key
        parent[["goall", "Start", "obstacle", "seed", ""][rng.integers(5)]] = junk
    else:
        parent.insert(int(key), junk)
    return data


def _texts(rng: np.random.Generator, n: int):
    base = json.dumps(BASE)
    for i in range(n):
        kind = i % 10
        if kind < 7:  # one to three structural edits
            data = BASE
            for _ in range(1 + rng.integers(3)):
                data = _mutate(rng, data)
            yield json.dumps(data)
        elif kind == 7:  # cut short
            yield base[: rng.integers(len(base))]
        elif kind == 8:  # random characters spliced in
            pos = rng.integers(len(base))
            yield base[:pos] + "".join(chr(c) for c in rng.integers(32, 127, 3)) + base[pos:]
        else:  # absurd values that are valid JSON
            scale = 10.0 ** rng.integers(-3, 8)
            data = copy.deepcopy(BASE)
            data["scenes"][0]["obstacles"][0] = [float(v) for v in rng.normal(0, scale, 3)]
            data["scenes"][1]["goal"] = [float(v) for v in rng.normal(0, scale, 2)]
            yield json.dumps(data)


@pytest.mark.filterwarnings("error::RuntimeWarning")  # no overflow on absurd values either
def test_malformed_scene_files_give_value_error_only(tmp_path):
    rng = np.random.default_rng(11)
    path = tmp_path / "s.json"
    outcomes = {"ok": 0, "error": 0}
    for text in _texts(rng, 400):
        path.write_text(text)
        try:
            scenes = load_scenes(path)
        except ValueError as e:
            assert str(path) in str(e), (text, e)
            outcomes["error"] += 1
            continue
        except Exception as e:  # noqa: BLE001  (the point of the test)
            pytest.fail(f"{type(e).__name__}: {e}\nfor the scenes file {text[:300]}")
        assert isinstance(scenes, Scenes) and np.isfinite(scenes.goal).all()
        assert np.all(scenes.obstacles[..., 2][scenes.mask] > 0)
        outcomes["ok"] += 1
    assert outcomes["ok"] >= 10 and outcomes["error"] >= 200, outcomes  # both paths exercised


def test_odd_files_give_value_error(tmp_path):
    (tmp_path / "binary.json").write_bytes(b"\xff\xfe\x00garbage")
    (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    (tmp_path / "folder.json").mkdir()
    for name in ("binary.json", "deep.json", "folder.json", "missing.json"):
        with pytest.raises(ValueError, match="scenes file"):
            load_scenes(tmp_path / name)


def _actions(rng: np.random.Generator, shape: tuple[int, ...]):
    """Random actions, most of them bad: NaN, inf, huge, wrong shape or type."""
    kind = rng.integers(12)
    if kind <= 2:
        return rng.uniform(-2, 2, shape).astype(np.float32)
    if kind == 3:
        return rng.normal(0, 1e30, shape)
    if kind == 4:
        a = rng.uniform(0, 0.6, shape)
        a.flat[rng.integers(a.size)] = [np.nan, np.inf, -np.inf][rng.integers(3)]
        return a
    if kind == 5:
        return rng.uniform(0, 0.6, shape[:-1] + (int(rng.integers(0, 5)) if rng.random() < 0.9 else 2,) * 2)
    if kind == 6:
        return np.zeros(shape, dtype=bool)
    if kind == 7:
        return [["0.3", "0.1"]] * shape[0] if len(shape) == 2 else ["0.3", "0.1"]
    if kind == 8:
        return [None, None]
    if kind == 9:
        return rng.integers(-(10**6), 10**6, shape)
    if kind == 10:
        return (rng.uniform(0, 0.6, shape) + 1j).astype(np.complex64)
    return [[0.1], [0.2, 0.3]]  # ragged


def test_random_actions_are_refused_or_clipped():
    rng = np.random.default_rng(5)
    params = FormationParams()
    env = FormationEnv()
    env.reset(seed=3)
    refused = stepped = 0
    for _ in range(300):
        before = env.state.pose.copy()
        try:
            obs, reward, terminated, truncated, info = env.step(_actions(rng, (2,)))
        except ValueError:
            np.testing.assert_array_equal(env.state.pose, before)  # a refused action changes nothing
            refused += 1
            continue
        stepped += 1
        assert np.isfinite(obs["agent_pos"]).all() and np.isfinite(obs["environment_state"]).all()
        assert math.isfinite(reward)
        v = np.hypot(*obs["agent_pos"][4:6])
        assert v <= params.v_max + 1e-5 and abs(obs["agent_pos"][6]) <= params.omega_max + 1e-5  # clipped
        if terminated or truncated:
            env.reset(seed=int(rng.integers(100)))
    assert refused > 50 and stepped > 50


def test_random_batched_actions_are_refused_or_clipped():
    rng = np.random.default_rng(6)
    venv = FormationVectorEnv(3)
    venv.reset(seed=10)
    for _ in range(150):
        before = venv.state.pose.copy()
        try:
            obs, reward, *_ = venv.step(_actions(rng, (3, 2)))
        except ValueError:
            np.testing.assert_array_equal(venv.state.pose, before)
            continue
        assert np.isfinite(obs["agent_pos"]).all() and np.isfinite(reward).all()
        assert (np.abs(obs["agent_pos"][:, 6]) <= FormationParams().omega_max + 1e-5).all()
