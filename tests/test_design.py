"""The README's "Design" claims: a new controller and a new obstacle encoding are each one new file
and one registry line; the bench, the env and the dataset writer then take them by name."""

import ast
import json
import textwrap
from pathlib import Path

import numpy as np

from lerobot_formation.bench.controllers import CONTROLLER_FACTORIES
from lerobot_formation.core.encodings.obstacle_grid import (
    ENCODING_REGISTRY,
    environment_state_dim,
    get_encoding,
)

STRAIGHT = '''
import numpy as np


class StraightToGoal:
    """Drive at 0.4 m/s, turning toward the goal."""

    name = "straight"

    def reset(self, view):
        self.goal = view.goal

    def act(self, view, idx):
        d = self.goal[idx] - view.pose[:, :2]
        error = np.angle(np.exp(1j * (np.arctan2(d[:, 1], d[:, 0]) - view.pose[:, 2])))
        return np.stack([np.full(len(idx), 0.4), np.clip(2.0 * error, -1.5, 1.5)], axis=-1)


def make_controller(name, params, args, bundle=None):
    return StraightToGoal()
'''

GOAL_ONLY = """
import numpy as np

from lerobot_formation.core.encodings.encoding import ObstacleEncoding, world_to_body


def encode(obstacles, mask, goal, pose, slots):
    return world_to_body(goal[:, None, :], pose)[:, 0].astype(np.float32)


ENCODING = ObstacleEncoding("goal-only", 0, 0, 2, True, encode, lambda slots: ["goal_bx", "goal_by"])
"""


def test_a_controller_is_one_file_and_one_registry_line(tmp_path, monkeypatch):
    from lerobot_formation.bench.cli import main

    (tmp_path / "straight_controller.py").write_text(textwrap.dedent(STRAIGHT))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(CONTROLLER_FACTORIES, "straight", "straight_controller:make_controller")
    out = tmp_path / "bench"
    argv = ["--controllers", "pac,straight", "--scenes", "random:2", "--no-figures", "--no-progress"]
    assert main([*argv, "--out", str(out)]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["straight"]["n_episodes"] == 2
    header = (out / "tables.md").read_text().splitlines()[2]
    assert header.index("straight (ours)") < header.index("pac (ours)")  # before PAC, as the paper's columns


def test_an_obstacle_encoding_is_one_file_and_one_registry_line(tmp_path, monkeypatch):
    from lerobot_formation.core.controllers.pac import PACController
    from lerobot_formation.core.episodes.rollout import rollout
    from lerobot_formation.core.world.sampling import sample_scenes
    from lerobot_formation.data.dataset_frames import dataset_features, episode_frames
    from lerobot_formation.envs.env import FormationEnv

    (tmp_path / "goal_only_encoding.py").write_text(textwrap.dedent(GOAL_ONLY))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(ENCODING_REGISTRY, "goal-only", "goal_only_encoding:ENCODING")
    assert get_encoding("goal-only").egocentric and environment_state_dim("goal-only") == 2
    names = dataset_features("goal-only")["observation.environment_state"]["names"]
    assert names == ["goal_bx", "goal_by"]
    scenes = sample_scenes([5])
    rec = rollout(scenes, PACController(), max_steps=20)
    frames = episode_frames(rec, scenes, 0, "goal-only")
    env = FormationEnv(obstacle_encoding="goal-only")
    obs, _ = env.reset(seed=5)
    assert env.observation_space.contains(obs)
    for t in range(int(rec.steps[0])):
        np.testing.assert_array_equal(frames["observation.environment_state"][t], obs["environment_state"])
        obs, *_ = env.step(rec.actions[0, t])
    # the team starts facing +y, so its body frame (x right, y ahead) is the world's, shifted
    assert scenes.start[0, 2] == np.pi / 2
    np.testing.assert_allclose(
        frames["observation.environment_state"][0], scenes.goal[0] - scenes.start[0, :2], atol=1e-5
    )


def _package_files() -> dict[str, ast.Module]:
    pkg = Path(__file__).resolve().parents[1] / "lerobot_formation"
    return {p.relative_to(pkg).as_posix(): ast.parse(p.read_text()) for p in pkg.rglob("*.py")}


def test_a_safety_filter_touches_at_most_three_files():
    """The shipped filter "cbf" is named (as a value, not in docs) and called in three files: its
    function in core/safety/filters.py, its name in the config's SAFETY_FILTERS and its call in the safety
    layer (core/safety/layer.py, whose FILTERS name it too).
    A new filter touches the same three (a bench controller that runs it is an optional registry line)."""
    named, called = set(), set()
    for path, tree in _package_files().items():
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and node.value == "cbf":
                named.add(path)
            if isinstance(node, ast.Name | ast.Attribute | ast.FunctionDef) and "cbf_filter" in (
                getattr(node, "id", None),
                getattr(node, "attr", None),
                getattr(node, "name", None),
            ):
                called.add(path)
    touched = (named - {"bench/controllers.py"}) | called
    assert touched == {
        "core/safety/filters.py",
        "policy/configuration_formation_diffusion.py",
        "core/safety/layer.py",
    }, touched


def test_the_library_takes_typed_arguments_not_argparse_namespaces():
    """Only the command-line entry points (``main`` and its argument helpers) see argparse results;
    the library's functions take dataclasses (ControllerOptions, BenchSettings, ReplanExperiment)."""
    wrong = []
    for path, tree in _package_files().items():
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and node.attr == "Namespace":
                wrong.append(f"{path}: argparse.Namespace")
            if isinstance(node, ast.FunctionDef) and node.name not in ("main", "paper_part"):
                params = [a.arg for a in node.args.args + node.args.kwonlyargs]
                if "args" in params:
                    wrong.append(f"{path}: {node.name}(args)")
    assert not wrong, wrong


def test_our_feature_keys_are_lerobots():
    from lerobot.utils import constants

    from lerobot_formation.compat import old_checkpoints
    from lerobot_formation.data import dataset_frames

    assert (dataset_frames.OBS_STATE, dataset_frames.OBS_ENV_STATE, dataset_frames.ACTION) == (
        constants.OBS_STATE,
        constants.OBS_ENV_STATE,
        constants.ACTION,
    )
    assert old_checkpoints.OBS_ENV_STATE == constants.OBS_ENV_STATE
