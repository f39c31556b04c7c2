"""Eval-video frames carry the episode time and, on the last frame, the outcome (issue 13)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plugin_helpers import tiny_config

from lerobot_formation.compat.lerobot_compat import keep_final_eval_frame
from lerobot_formation.envs.env_config import FormationEnvConfig
from lerobot_formation.envs.render import FINAL_FRAME_KEY, OUTCOME_COLORS, annotate
from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy

STRAIGHT = np.array([0.6, 0.0], np.float32)  # full speed ahead; the team starts at (0, 0) facing +y
SCENES = {
    # an obstacle in the right leader's (L2's) way
    "collision": {"obstacles": [[0.6, 1.6, 0.4]], "goal": [5, 5]},
    "success": {"obstacles": [], "goal": [0, 2]},
    "timeout": {"obstacles": [], "goal": [5, 5]},
}
TEXTS = {
    "collision": "collision: L2 hit an obstacle at t = 1.9 s",
    "success": "success: goal reached at t = 2.9 s",
    "timeout": "timeout: goal not reached by t = 0.8 s",
}


def banner_rows(frame: np.ndarray) -> np.ndarray:
    return frame[-frame.shape[0] // 16 :]


def stamp_box(frame: np.ndarray) -> np.ndarray:
    return frame[: frame.shape[0] // 8, : frame.shape[1] // 3]


def run(kind: str):
    """(annotated frames, raw frames, overlay) of one episode through the eval env stack, plus one step
    of the frozen env after the end."""
    env = FormationEnvConfig(episode_length=8 if kind == "timeout" else 40).make_env_factory()()
    env.reset(options={"scene": SCENES[kind]})
    frames, raw = [env.render()], [env.unwrapped.render()]
    while True:
        *_, terminated, truncated, _ = env.step(STRAIGHT)
        frames.append(env.render())
        raw.append(env.unwrapped.render())
        if terminated or truncated:
            break
    env.step(STRAIGHT)  # LeRobot's FreezeAfterEpisodeEnd replays the end: the frame stays the last one
    frames.append(env.render())
    return frames, raw, env.env


def test_annotate_keeps_shape_and_dtype_and_draws():
    frame = np.full((256, 256, 3), 255, np.uint8)
    out = annotate(frame, "t = 1.0 s", ("collision", "collision: L1 hit an obstacle at t = 1.0 s"))
    assert out.shape == frame.shape and out.dtype == np.uint8
    assert (stamp_box(out) != 255).any()
    np.testing.assert_array_equal(np.median(banner_rows(out), axis=(0, 1)), OUTCOME_COLORS["collision"])
    assert (frame == 255).all()  # the input is not drawn on
    tiny = np.zeros((32, 32, 3), np.uint8)
    np.testing.assert_array_equal(annotate(tiny, "t = 1.0 s"), tiny)  # no room for text


@pytest.mark.parametrize("kind", ["collision", "success", "timeout"])
def test_every_frame_has_its_time_and_only_the_last_the_outcome(kind):
    frames, raw, overlay = run(kind)
    assert overlay._outcome == (kind, TEXTS[kind])
    final, before = frames[-1], frames[:-2]
    for k, (frame, plain) in enumerate(zip(frames[:-1], raw, strict=True)):
        assert frame.shape == plain.shape and frame.dtype == np.uint8
        assert (stamp_box(frame) != stamp_box(plain)).any(), f"frame {k} has no time stamp"
    # The time changes from frame to frame (t = 0.0 s, 0.1 s, ...).
    assert all((stamp_box(a) != stamp_box(b)).any() for a, b in zip(before, before[1:], strict=False))
    # No banner before the end: outside the stamp, a frame is the plain render.
    for frame, plain in zip(before, raw, strict=False):
        np.testing.assert_array_equal(banner_rows(frame), banner_rows(plain))
    assert (banner_rows(frames[-2]) != banner_rows(raw[-1])).any()
    np.testing.assert_array_equal(np.median(banner_rows(final), axis=(0, 1)), OUTCOME_COLORS[kind])
    np.testing.assert_array_equal(final, frames[-2])  # frozen after the end


def test_lerobot_eval_video_ends_on_the_outcome_frame(monkeypatch, tmp_path):
    """LeRobot's eval_policy with a policy that drives straight: the video it writes ends on the frame with the
    outcome banner with our rollout wrapper, and one frame earlier without it (LeRobot's slice)."""
    from lerobot.scripts import lerobot_eval

    # The CLIs import lerobot_eval before the plugin; here the test imports it after, so patch now.
    assert keep_final_eval_frame(FINAL_FRAME_KEY) and keep_final_eval_frame(FINAL_FRAME_KEY)  # idempotent
    assert lerobot_eval.rollout._formation_final_frame and not hasattr(
        lerobot_eval.rollout.__wrapped__, "_formation_final_frame"
    )

    policy = FormationDiffusionPolicy(tiny_config())  # eval_policy wants a PreTrainedPolicy
    policy.select_action = lambda observation: torch.from_numpy(STRAIGHT)[None]

    def videos(rollout) -> list[np.ndarray]:
        written = []
        env = FormationEnvConfig(episode_length=5).create_envs(1)["formation"][0]  # wraps rollout if not yet
        assert env.metadata[FINAL_FRAME_KEY] and lerobot_eval.rollout._formation_final_frame
        monkeypatch.setattr(lerobot_eval, "rollout", rollout)
        monkeypatch.setattr(lerobot_eval, "write_video", lambda path, frames, fps: written.append(frames))
        try:
            identity = lambda x: x  # noqa: E731
            lerobot_eval.eval_policy(
                env, policy, identity, identity, identity, identity, n_episodes=1,
                max_episodes_rendered=1, videos_dir=tmp_path, start_seed=0,
            )  # fmt: skip
        finally:
            env.close()
        (frames,) = written
        return list(frames)

    ours = videos(lerobot_eval.rollout)
    stock = videos(lerobot_eval.rollout.__wrapped__)
    assert len(ours) == len(stock) == 5  # one frame per step; LeRobot's has the reset frame first
    assert np.median(banner_rows(ours[-1]), axis=(0, 1)).tolist() == list(OUTCOME_COLORS["timeout"])
    # LeRobot's own slice stops before the ending step: no banner.
    assert np.median(banner_rows(stock[-1]), axis=(0, 1)).tolist() != list(OUTCOME_COLORS["timeout"])
    np.testing.assert_array_equal(ours[:-1], stock[1:])  # the same frames, shifted by one


def test_a_gym_made_env_gets_the_same_overlay_outside_its_time_limit():
    import gymnasium as gym

    from lerobot_formation.envs import ENV_ID
    from lerobot_formation.envs.render import EpisodeOverlay

    env = EpisodeOverlay(gym.make(ENV_ID, render_mode="rgb_array", max_episode_steps=8))
    env.reset(options={"scene": SCENES["timeout"]})
    for _ in range(8):
        *_, terminated, truncated, _ = env.step(STRAIGHT)
    assert truncated and not terminated
    assert env._outcome == ("timeout", TEXTS["timeout"])
    np.testing.assert_array_equal(
        np.median(banner_rows(env.render()), axis=(0, 1)), OUTCOME_COLORS["timeout"]
    )
