"""The gymnasium env, its vector form, and bad input."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from lerobot_formation.core.controllers.pac import PACController
from lerobot_formation.core.episodes.rollout import rollout
from lerobot_formation.core.world.sampling import sample_scenes
from lerobot_formation.core.world.scene_files import save_scenes
from lerobot_formation.envs import ENV_ID
from lerobot_formation.envs.env import FormationEnv
from lerobot_formation.envs.vector_env import FormationVectorEnv


def test_check_env_passes():
    env = gym.make(ENV_ID, render_mode="rgb_array")
    check_env(env.unwrapped, skip_render_check=False)


def test_registered_spec_and_metadata():
    env = gym.make(ENV_ID)
    assert env.spec.max_episode_steps == 600
    assert env.unwrapped.metadata["render_fps"] == 10


def rollout_env(env, seed, n=30):
    obs, _ = env.reset(seed=seed)
    traj = [obs["agent_pos"]]
    for t in range(n):
        obs, *_ = env.step(np.array([0.4, 0.3 * np.sin(t / 5)], np.float32))
        traj.append(obs["agent_pos"])
    return np.array(traj)


def test_same_seed_same_scene_and_trajectory():
    a, b = FormationEnv(), FormationEnv()
    np.testing.assert_array_equal(rollout_env(a, 5), rollout_env(b, 5))
    np.testing.assert_array_equal(a.scene.obstacles, b.scene.obstacles)
    c = FormationEnv()
    c.reset(seed=6)
    assert not np.array_equal(a.scene.obstacles, c.scene.obstacles)


def test_vector_env_matches_single_env():
    B, steps = 4, 25
    venv = FormationVectorEnv(B)
    singles = [FormationEnv() for _ in range(B)]
    vobs, _ = venv.reset(seed=100)
    for i, e in enumerate(singles):
        e.reset(seed=100 + i)
    rng = np.random.default_rng(0)
    for _ in range(steps):
        a = rng.uniform([0, -1.5], [0.6, 1.5], size=(B, 2)).astype(np.float32)
        vobs, vr, vterm, _, _ = venv.step(a)
        outs = [e.step(a[i]) for i, e in enumerate(singles)]
        for i in range(B):
            if not vterm[i]:
                np.testing.assert_array_equal(vobs["agent_pos"][i], outs[i][0]["agent_pos"])
                np.testing.assert_array_equal(vobs["environment_state"][i], outs[i][0]["environment_state"])
                assert vr[i] == pytest.approx(outs[i][1], abs=0, rel=0)


def test_env_and_batched_rollout_agree_for_pac():
    scenes = sample_scenes([0, 1])
    rec = rollout(scenes, PACController())
    for b in range(2):
        env = FormationEnv()
        env.reset(options={"scene": scenes[b].to_list()[0]})
        ctrl = PACController()
        ctrl.reset(env.teams.perceive())
        for t in range(int(rec.steps[b])):
            a = ctrl.act(env.teams.perceive(), np.array([0]))[0]
            np.testing.assert_allclose(a, rec.actions[b, t], rtol=0, atol=1e-12)
            _, _, term, _, info = env.step(a)
        assert term and info["is_success"] == (rec.outcome[b] == 1)


def test_reset_options_scene_and_scenes_file(tmp_path):
    sc = sample_scenes([42, 43])
    save_scenes(sc, tmp_path / "s.json")
    env = FormationEnv(scenes_file=str(tmp_path / "s.json"))
    env.reset(seed=1)
    np.testing.assert_allclose(env.scene.obstacles[env.scene.mask], sc[1].obstacles[sc[1].mask])
    with pytest.raises(ValueError, match="seed 2 is past the end of scenes file"):  # no wrap-around
        env.reset(seed=2)
    env2 = FormationEnv()
    _, info = env2.reset(options={"scene": {"obstacles": [[3, 3, 0.5]], "goal": [4, 6]}})
    assert info["is_success"] is False
    np.testing.assert_allclose(env2._obs()["environment_state"][49:], [4, 6])


def test_info_keys_and_render():
    env = FormationEnv(render_mode="rgb_array")
    _, info = env.reset(seed=0)
    assert {"is_success", "is_collision", "formation_error", "clearance", "midpoint_clearance"} <= set(info)
    env.step(np.array([0.5, 0.0], np.float32))
    img = env.render()
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 4  # obstacles, goal, agents, edges drawn


@pytest.mark.parametrize(
    ("action", "match"),
    [
        (np.zeros(3, np.float32), "shape \\(2,\\)"),
        (np.zeros((1, 2), np.float32), "shape \\(2,\\)"),
        (np.array([np.nan, 0.0], np.float32), "finite, got \\[nan, 0.0\\]"),
        (np.array([0.1, np.inf]), "finite"),
        (np.array(["a", "b"]), "dtype"),
    ],
)
def test_bad_actions_raise_naming_value(action, match):
    env = FormationEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match=match):
        env.step(action)


def test_vector_env_bad_action_shape():
    venv = FormationVectorEnv(3)
    venv.reset(seed=0)
    with pytest.raises(ValueError, match="shape \\(3, 2\\)"):
        venv.step(np.zeros((2, 2)))


def test_vector_env_autoreset_same_step():
    venv = FormationVectorEnv(2, max_episode_steps=3)
    venv.reset(seed=0)
    for _ in range(2):
        _, _, _, trunc, infos = venv.step(np.zeros((2, 2)))
        assert not trunc.any()
    obs, _, _, trunc, infos = venv.step(np.zeros((2, 2)))
    assert trunc.all() and "final_obs" in infos and infos["_final_info"].all()
    assert (venv._steps == 0).all()
