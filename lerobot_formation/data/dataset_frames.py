"""What a PAC dataset holds: its LeRobot features and the frames of one recorded episode.

The observations are ``core.perception.observation``'s, the builder the env uses, so a policy trained on the
dataset sees in the env what it saw in training (``tests/core/test_house.py`` checks it frame by
frame). Under realistic conditions (``core.perception.conditions``) the frames hold what the team observed
during the rollout (``EpisodeRecords.observations``: noisy pose, sensed obstacles) and the commands
PAC sent (``EpisodeRecords.commands``, clipped), not the executed velocities.
"""

from __future__ import annotations

import numpy as np

from lerobot_formation.core.encodings.obstacle_grid import get_encoding
from lerobot_formation.core.episodes.rollout import EpisodeRecords
from lerobot_formation.core.perception.observation import STATE_DIM, STATE_NAMES, observe, observed_velocities
from lerobot_formation.core.world.dynamics import FormationParams, clip_action
from lerobot_formation.core.world.scenes import Scenes

# LeRobot's feature keys (``lerobot.utils.constants``; not imported here: that module loads torch,
# which the generator's numpy workers do without; tests/test_design.py checks they are equal).
OBS_STATE = "observation.state"
OBS_ENV_STATE = "observation.environment_state"
ACTION = "action"

FPS = 10
MAX_OBSTACLES = 5


def dataset_features(obstacle_encoding: str = "grid", scene_slots: int = MAX_OBSTACLES) -> dict:
    """LeRobot features of a PAC dataset; ``scene_slots`` obstacle rows in ``scene.obstacles`` (every
    obstacle of every scene, whatever the observation encodes)."""
    grid_names = get_encoding(obstacle_encoding).names(get_encoding(obstacle_encoding).slots(None))
    return {
        OBS_STATE: {"dtype": "float32", "shape": (STATE_DIM,), "names": STATE_NAMES},
        OBS_ENV_STATE: {
            "dtype": "float32",
            "shape": (len(grid_names),),
            "names": grid_names,
        },
        ACTION: {"dtype": "float32", "shape": (2,), "names": ["v", "omega"]},
        "scene.seed": {"dtype": "int64", "shape": (1,), "names": None},
        "scene.obstacles": {
            "dtype": "float32",
            "shape": (3 * scene_slots,),
            "names": [f"obstacle_{k}_{c}" for k in range(scene_slots) for c in ("x", "y", "r")],
        },
        "scene.goal": {"dtype": "float32", "shape": (2,), "names": ["x", "y"]},
        "scene.start": {"dtype": "float32", "shape": (3,), "names": ["x", "y", "phi"]},
    }


def episode_frames(
    rec: EpisodeRecords, scenes: Scenes, b: int, obstacle_encoding: str, scene_slots: int = MAX_OBSTACLES
) -> dict[str, np.ndarray]:
    """The frames of episode b as arrays (n, ...): observation before action t, and action t (with
    recorded observations, ``rec.observations``: those, and the commands sent)."""
    n = int(rec.steps[b])
    poses = rec.poses[b, :n]
    actions = rec.actions[b, :n]
    if rec.observations is not None:  # under conditions: what the team observed, what PAC sent
        seen = {k: v[b, :n] for k, v in rec.observations.items()}
        if rec.commands is not None:
            actions = clip_action(rec.commands[b, :n], FormationParams())
    else:
        one = slice(b, b + 1)  # the episode's scene, observed at each of its n poses
        seen = observe(
            poses,
            observed_velocities(poses, actions),
            scenes.obstacles[one],
            scenes.mask[one],
            scenes.goal[one],
            obstacle_encoding,
        )
    real = scenes.obstacles[b][scenes.mask[b]]
    if len(real) > scene_slots:
        raise ValueError(f"scene {b} has {len(real)} obstacles, more than the dataset's {scene_slots} slots")
    obs_list = np.zeros((scene_slots, 3), np.float32)
    obs_list[: len(real)] = real
    return {
        OBS_STATE: seen["agent_pos"],
        OBS_ENV_STATE: seen["environment_state"],
        ACTION: actions.astype(np.float32),
        "scene.seed": np.full((n, 1), scenes.seeds[b], dtype=np.int64),
        "scene.obstacles": np.repeat(obs_list.reshape(1, -1), n, axis=0),
        "scene.goal": np.repeat(scenes.goal[b : b + 1].astype(np.float32), n, axis=0),
        "scene.start": np.repeat(scenes.start[b : b + 1].astype(np.float32), n, axis=0),
    }
