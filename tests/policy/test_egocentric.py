"""The egocentric-obstacles preprocessor step: right numbers, saved with the checkpoint, clear errors."""

import numpy as np
import pytest
import torch
from lerobot.processor import PolicyProcessorPipeline
from lerobot.utils.constants import OBS_ENV_STATE, OBS_STATE
from plugin_helpers import formation_features, tiny_config

from lerobot_formation.core.encodings.obstacle_grid import environment_state
from lerobot_formation.core.world.sampling import sample_scenes
from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy
from lerobot_formation.policy.processor_formation_diffusion import (
    EgocentricObstaclesProcessorStep,
    egocentric_environment_state,
    make_formation_diffusion_pre_post_processors,
)

# normalisation statistics of the processor tests (the state range covers the world batches below)
STATS = {
    OBS_STATE: {"min": torch.full((7,), -1.0), "max": torch.full((7,), 6.0)},
    "action": {"min": torch.tensor([0.0, -1.5]), "max": torch.tensor([0.6, 1.5])},
}


def world_batch(b=6, seed=0):
    scenes = sample_scenes(np.arange(b))
    env = environment_state(scenes.obstacles, scenes.mask, scenes.goal, "grid+list")
    rng = np.random.default_rng(seed)
    pose = np.c_[rng.uniform(0, 5, (b, 2)), rng.uniform(-np.pi, np.pi, b)]
    state = np.c_[pose[:, :2], np.cos(pose[:, 2]), np.sin(pose[:, 2]), rng.normal(size=(b, 3))]
    return scenes, pose, state.astype(np.float32), env


def test_goal_and_obstacles_in_the_midpoint_frame_nearest_first():
    scenes, pose, state, env = world_batch()
    out = egocentric_environment_state(torch.tensor(state), torch.tensor(env), 5).numpy()
    for b in range(len(pose)):
        c, s = np.cos(pose[b, 2]), np.sin(pose[b, 2])
        rot = np.array([[c, -s], [s, c]])  # world <- ego; ego = rot^T d, i.e. d @ rot
        obs = scenes.obstacles[b][scenes.mask[b]]
        ego = (obs[:, :2] - pose[b, :2]) @ rot
        order = np.argsort(np.linalg.norm(ego, axis=1) - obs[:, 2])
        rows = np.zeros((5, 3))
        rows[: len(order)] = np.c_[ego[order], obs[order, 2]]
        np.testing.assert_allclose(out[b, 51:], rows.ravel(), atol=1e-5)
        np.testing.assert_allclose(out[b, 49:51], (scenes.goal[b] - pose[b, :2]) @ rot, atol=1e-5)
        np.testing.assert_array_equal(out[b, :49], env[b, :49])  # the grid is kept
    # Facing the goal straight on: the goal lies on the +x axis of the midpoint's frame.
    st = torch.tensor([[0, 0, np.cos(np.pi / 4), np.sin(np.pi / 4), 0, 0, 0]], dtype=torch.float32)
    goal = egocentric_environment_state(st, torch.tensor(env[:1]), 5)[0, 49:51]
    torch.testing.assert_close(goal, torch.tensor([np.hypot(5, 5), 0.0], dtype=torch.float32))


def test_history_windows_use_each_frames_own_pose():
    _, _, state, env = world_batch()
    st, en = torch.tensor(state), torch.tensor(env)
    hist = egocentric_environment_state(torch.stack([st, st.flip(0)], 1), torch.stack([en, en.flip(0)], 1), 5)
    torch.testing.assert_close(hist[:, 0], egocentric_environment_state(st, en, 5))
    torch.testing.assert_close(hist[:, 1], egocentric_environment_state(st.flip(0), en.flip(0), 5))


def test_step_sits_before_the_normalizer_and_loads_back(tmp_path):
    inputs, outputs = formation_features(env_dim=66)
    cfg = tiny_config(
        input_features=inputs,
        output_features=outputs,
        egocentric_obstacles=True,
        obstacle_encoding="grid+list",
    )
    pre, _ = make_formation_diffusion_pre_post_processors(cfg, STATS)
    names = [type(s).__name__ for s in pre.steps]
    assert names.index("EgocentricObstaclesProcessorStep") == names.index("NormalizerProcessorStep") - 1
    pre.save_pretrained(tmp_path)
    loaded = PolicyProcessorPipeline.from_pretrained(tmp_path, config_filename="policy_preprocessor.json")
    _, _, state, env = world_batch(2)
    obs = {OBS_STATE: torch.tensor(state), OBS_ENV_STATE: torch.tensor(env)}
    a, b = pre(dict(obs)), loaded(dict(obs))
    torch.testing.assert_close(a[OBS_ENV_STATE], b[OBS_ENV_STATE])
    torch.testing.assert_close(
        a[OBS_ENV_STATE], egocentric_environment_state(obs[OBS_STATE], obs[OBS_ENV_STATE], 5)
    )
    # Off by default: the paper's world-frame observation passes through.
    plain, _ = make_formation_diffusion_pre_post_processors(
        tiny_config(input_features=inputs, output_features=outputs, obstacle_encoding="grid+list"), STATS
    )
    torch.testing.assert_close(plain(dict(obs))[OBS_ENV_STATE], obs[OBS_ENV_STATE])


def test_egocentric_needs_the_obstacle_list():
    inputs, outputs = formation_features(env_dim=51)
    with pytest.raises(ValueError, match=r"egocentric_obstacles=true needs .*'grid\+list'.*got \(51,\)"):
        FormationDiffusionPolicy(
            tiny_config(input_features=inputs, output_features=outputs, egocentric_obstacles=True)
        )
    with pytest.raises(
        ValueError, match=r"grid\+list encoding \(66 values\), got observation.environment_state with 51"
    ):
        egocentric_environment_state(torch.zeros(1, 7), torch.zeros(1, 51), 5)
    with pytest.raises(ValueError, match=r"need observation.state and observation.environment_state"):
        EgocentricObstaclesProcessorStep().observation({OBS_ENV_STATE: torch.zeros(1, 66)})
