"""Scenes: seeded sampling, validity, JSON, bad input; the formation graph."""

import json

import numpy as np
import pytest

from lerobot_formation.core.encodings.obstacle_grid import environment_state, obstacle_grid
from lerobot_formation.core.world.formation_graph import FormationGraph
from lerobot_formation.core.world.presets import SceneConfig
from lerobot_formation.core.world.sampling import SamplingReport, sample_scenes
from lerobot_formation.core.world.scene_files import load_scenes, save_scenes, scenes_from_list
from lerobot_formation.core.world.validity import passage_exists, scene_validity


def test_scene_is_pure_function_of_seed():
    batch = sample_scenes([3, 11, 7])
    alone = sample_scenes([11])
    np.testing.assert_array_equal(batch[1].obstacles, alone.obstacles)
    assert not np.array_equal(batch[0].obstacles, batch[1].obstacles)


def test_sampled_scenes_follow_spec_and_are_valid():
    report = SamplingReport()
    sc = sample_scenes(np.arange(50), report=report)
    n = sc.mask.sum(1)
    assert n.min() >= 3 and n.max() <= 5
    r = sc.obstacles[..., 2][sc.mask]
    assert r.min() >= 0.3 and r.max() <= 0.8
    xy = sc.obstacles[..., :2][sc.mask]
    assert xy.min() >= 1.5 and xy.max() <= 6.0
    assert scene_validity(sc, SceneConfig())[0].all()
    assert report.accepted == 50 and report.drawn > 50  # most draws are rejected (goal in the field)


def test_passage_check_finds_enclosed_goal():
    ring = [
        [5 + 1.6 * np.cos(a), 5 + 1.6 * np.sin(a), 0.8] for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)
    ]
    closed = scenes_from_list([{"obstacles": ring, "goal": [5, 5]}], check=False)
    open_ = scenes_from_list([{"obstacles": ring[:3], "goal": [5, 5]}], check=False)
    cfg = SceneConfig()
    assert not passage_exists(closed, cfg)[0]
    assert passage_exists(open_, cfg)[0]


def test_json_round_trip(tmp_path):
    sc = sample_scenes([1, 2])
    save_scenes(sc, tmp_path / "s.json")
    back = load_scenes(tmp_path / "s.json")
    np.testing.assert_allclose(back.obstacles[back.mask], sc.obstacles[sc.mask])
    np.testing.assert_allclose(back.goal, sc.goal)


def test_start_is_optional_and_defaults_to_paper(tmp_path):
    sc = scenes_from_list([{"obstacles": [[3, 3, 0.5]], "goal": [5, 5]}])
    np.testing.assert_allclose(sc.start[0], [0, 0, np.pi / 2])


@pytest.mark.parametrize(
    ("scene", "match"),
    [
        ({"obstacles": [[3, 3, -0.5]], "goal": [5, 5]}, "non-positive radius -0.5"),
        ({"obstacles": [[0.5, 0, 0.3]], "goal": [5, 5]}, "over the start formation"),
        ({"obstacles": [[5, 5, 0.5]], "goal": [5.1, 5]}, "goal \\[5.1, 5.0\\] lies inside obstacle"),
        ({"obstacles": [[3, float("nan"), 0.5]], "goal": [5, 5]}, "non-finite"),
        ({"obstacles": [[3, 3]], "goal": [5, 5]}, "obstacles must be"),
        ({"obstacles": [], "goal": [5]}, "goal must be"),
    ],
)
def test_impossible_scenes_are_rejected(scene, match):
    with pytest.raises(ValueError, match=match):
        scenes_from_list([scene])


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("{not json", "not valid JSON"),
        ('{"foo": []}', "key 'scenes'"),
        ('{"scenes": [{"goal": [1, 1]}]}', "obstacles"),
    ],
)
def test_malformed_scenes_file(tmp_path, text, match):
    f = tmp_path / "bad.json"
    f.write_text(text)
    with pytest.raises(ValueError, match=match):
        load_scenes(f)


def test_missing_scenes_file(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        load_scenes(tmp_path / "nope.json")


def test_obstacle_grid_cells_and_shared_cell():
    sc = scenes_from_list(
        [{"obstacles": [[2.5, 3.7, 0.4], [2.2, 3.1, 0.6], [5.9, 1.6, 0.3]], "goal": [5, 5]}]
    )
    g = obstacle_grid(sc.obstacles, sc.mask).reshape(7, 7)
    assert g[1, 2] == pytest.approx(0.6)  # two centres in cell (1, 2): the larger radius
    assert g[4, 0] == pytest.approx(0.3)
    assert np.count_nonzero(g) == 2
    es = environment_state(sc.obstacles, sc.mask, sc.goal)
    assert es.shape == (1, 51) and es.dtype == np.float32
    np.testing.assert_allclose(es[0, 49:], [5, 5])
    assert environment_state(sc.obstacles, sc.mask, sc.goal, "grid+list").shape == (1, 66)


def test_graph_checks():
    g = FormationGraph()
    assert g.is_rigid() and g.n_followers == 2
    with pytest.raises(ValueError, match="unknown agent 'F3'"):
        FormationGraph(edges=(("L1", "L2"), ("L2", "F1"), ("L1", "F1"), ("L2", "F3"), ("F1", "F2")))
    with pytest.raises(ValueError, match="not rigid"):
        FormationGraph(edges=(("L1", "L2"), ("L1", "F1"), ("L2", "F2"), ("F1", "F2")), distances=(1, 1, 1, 1))


def test_triangle_graph_with_one_follower():
    h = np.sqrt(0.75)
    g = FormationGraph(
        agents=("L1", "L2", "F1"),
        edges=(("L1", "L2"), ("L1", "F1"), ("L2", "F1")),
        distances=(1.0, 1.0, 1.0),
        template=((-0.5, 0.0), (0.5, 0.0), (0.0, -h)),
    )
    assert g.is_rigid()
    json.dumps(g.edges)
