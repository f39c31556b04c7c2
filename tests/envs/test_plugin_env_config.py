"""The ``formation`` env config: features, sync and async vector envs, formation metrics."""

import json
import pickle

import gymnasium as gym
import numpy as np
import pytest
from lerobot.configs import FeatureType
from lerobot.envs.configs import EnvConfig
from lerobot.envs.factory import make_env
from lerobot.envs.utils import NEW_ROLLOUT_OPTION, env_to_policy_features, preprocess_observation
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_formation.core.episodes.metrics import FLAG_KEYS, METRIC_KEYS
from lerobot_formation.envs.env_config import FormationEnvConfig
from lerobot_formation.envs.episode_metrics import INFO_KEY

CIRCLE = np.array([0.5, 1.5], np.float32)  # [v, omega]: a tight circle, never reaches the goal


def test_registered_and_features_include_action():
    assert EnvConfig.get_choice_class("formation") is FormationEnvConfig
    cfg = FormationEnvConfig()
    assert cfg.features[ACTION].type is FeatureType.ACTION and cfg.features[ACTION].shape == (2,)
    policy_features = env_to_policy_features(cfg)
    assert policy_features[OBS_STATE].shape == (7,)
    assert policy_features[OBS_ENV_STATE].type is FeatureType.ENV
    assert policy_features[OBS_ENV_STATE].shape == (51,)
    with_list = env_to_policy_features(FormationEnvConfig(obstacle_encoding="grid+list"))
    assert with_list[OBS_ENV_STATE].shape == (66,)


def test_factory_pickles_by_reference():
    factory = FormationEnvConfig(episode_length=5).make_env_factory()
    blob = pickle.dumps(factory)
    assert b"lerobot_formation.envs.env_config" in blob
    env = pickle.loads(blob)()
    assert env.get_wrapper_attr("_max_episode_steps") == 5
    env.close()


def run_until_all_done(vec, seeds, action=CIRCLE, max_steps=100):
    obs, info = vec.reset(seed=seeds, options={NEW_ROLLOUT_OPTION: True})
    done = np.zeros(vec.num_envs, bool)
    finals = []
    for _ in range(max_steps):
        obs, reward, terminated, truncated, info = vec.step(np.tile(action, (vec.num_envs, 1)))
        if "final_info" in info:
            finals.append(info["final_info"])
        done |= terminated | truncated
        if done.all():
            break
    return obs, finals, done


def test_sync_envs_through_lerobot_make_env(tmp_path):
    log = tmp_path / "metrics.jsonl"
    cfg = FormationEnvConfig(episode_length=6, episode_metrics_path=str(log))
    envs = make_env(cfg, n_envs=2, use_async_envs=False)
    vec = envs["formation"][0]
    try:
        assert isinstance(vec, gym.vector.SyncVectorEnv)
        assert vec.metadata["autoreset_mode"] is gym.vector.AutoresetMode.SAME_STEP
        assert vec.call("_max_episode_steps") == (6, 6)
        assert vec.unwrapped.metadata["render_fps"] == cfg.fps
        assert vec.call("task_description")[0]
        obs, finals, done = run_until_all_done(vec, [3, 4])
        assert vec.envs[0].render().dtype == np.uint8
        assert done.all()
        batch = preprocess_observation(obs)
        assert batch[OBS_STATE].shape == (2, 7) and batch[OBS_ENV_STATE].shape == (2, 51)
        (final,) = finals  # both episodes time out at step 6, together
        metrics = final[INFO_KEY]
        assert list(metrics["outcome"]) == ["timeout", "timeout"]
        assert list(metrics["reset_seed"]) == [3, 4]
        assert set(METRIC_KEYS) | set(FLAG_KEYS) <= set(metrics)
        assert np.all(metrics["steps"] == 6) and np.all(np.isfinite(metrics["mean_formation_error"]))
        # A finished sub-env is frozen (LeRobot's FreezeAfterEpisodeEnd): no new episode, no new line.
        vec.step(np.tile(CIRCLE, (2, 1)))
    finally:
        vec.close()
    lines = [json.loads(line) for line in log.read_text().splitlines()]
    assert sorted(r["reset_seed"] for r in lines) == [3, 4]
    assert all(r["outcome"] == "timeout" and r["steps"] == 6 for r in lines)


def test_async_envs_with_forkserver_workers(tmp_path):
    log = tmp_path / "metrics.jsonl"
    cfg = FormationEnvConfig(episode_length=4, episode_metrics_path=str(log))
    vec = cfg.create_envs(n_envs=2, use_async_envs=True)["formation"][0]
    try:
        assert isinstance(vec, gym.vector.AsyncVectorEnv)
        assert vec.call("_max_episode_steps") == (4, 4)
        _, finals, done = run_until_all_done(vec, [10, 11])
        assert done.all()
        assert list(finals[0][INFO_KEY]["reset_seed"]) == [10, 11]
        frames = vec.call("render")
        assert frames[0].ndim == 3 and frames[0].dtype == np.uint8
    finally:
        vec.close()
    assert len(log.read_text().splitlines()) == 2  # written by the worker processes


@pytest.mark.parametrize("n_envs", [0, -1])
def test_bad_n_envs(n_envs):
    with pytest.raises(ValueError, match=f"n_envs must be >= 1, got {n_envs}"):
        FormationEnvConfig().create_envs(n_envs)
