"""Figures: labelled axes, real scene names, true counts, failure grids with the collision marked,
controllers side by side and the success chart's Wilson intervals."""

import dataclasses

import numpy as np
import pytest
from matplotlib.container import ErrorbarContainer

from lerobot_formation.bench.plots import figures
from lerobot_formation.bench.scene_sets import scene_set_presets
from lerobot_formation.core.controllers.pac import PACController
from lerobot_formation.core.episodes import metrics
from lerobot_formation.core.episodes.rollout import COLLISION, SUCCESS, TIMEOUT, EpisodeRecords, rollout
from lerobot_formation.core.world.dynamics import FormationParams, agent_positions, initial_state
from lerobot_formation.core.world.geometry import agent_clearances
from lerobot_formation.core.world.sampling import sample_scenes
from lerobot_formation.core.world.scene_files import scenes_from_list
from lerobot_formation.core.world.scenes import Scenes

PAPER_START = [0.0, 0.0, np.pi / 2]  # midpoint at the origin, heading +y


class Straight:
    """Drives the midpoint straight ahead at ``v`` m/s (0: stands still, a timeout)."""

    name = "straight"

    def __init__(self, v: float):
        self.v = v

    def reset(self, view) -> None:
        pass

    def act(self, view, idx):
        return np.tile([self.v, 0.0], (len(idx), 1))


@pytest.fixture(scope="module")
def mixed():
    """Scene 0: an obstacle right of the heading, hit by the right-hand agents; scene 1: clear (no
    seeds, as in a scenes file). Driving straight: a collision, and a timeout after 30 steps."""
    scenes = scenes_from_list(
        [
            {"obstacles": [[0.5, 2.0, 0.4]], "goal": [5.0, 5.0], "start": PAPER_START},
            {"obstacles": [[4.0, 1.0, 0.5]], "goal": [5.0, 5.0], "start": PAPER_START},
        ],
        check=False,
    )
    return scenes, rollout(scenes, Straight(0.5), max_steps=30)


@pytest.fixture(scope="module")
def pac_run():
    scenes = sample_scenes(1_000_000 + np.arange(3))
    return scenes, rollout(scenes, PACController())


@pytest.fixture
def captured(monkeypatch):
    """The figures drawn, kept open instead of only written."""
    figs = []
    real = figures._save

    def keep(fig, path, dpi=110):
        figs.append(fig)
        fig.savefig(path, dpi=40)
        return path

    monkeypatch.setattr(figures, "_save", keep)
    yield figs
    monkeypatch.setattr(figures, "_save", real)
    for fig in figs:
        figures.plt.close(fig)


def _take(rec: EpisodeRecords, idx) -> EpisodeRecords:
    """The episodes ``idx`` of ``rec`` (repeats allowed)."""
    return rec.take(idx)


def _panels(fig):
    return [ax for ax in fig.axes if ax.axison]


def _assert_labelled(fig):
    """Both axes labelled, x with its unit (a y axis of counts, "episodes", has none)."""
    for ax in _panels(fig):
        assert "[" in ax.get_xlabel() and ax.get_ylabel(), (ax.get_xlabel(), ax.get_ylabel())


def test_scene_label_is_the_preset_the_index_and_the_seed(mixed, pac_run):
    assert figures.scene_label(mixed[0], 1) == "scene 1"  # no seed (given by hand), no preset known
    assert figures.scene_label(pac_run[0], 2) == "scene 2, seed 1000002"
    twice = Scenes.concat([pac_run[0][:2], pac_run[0][:2]])  # the hard suite: each preset from seed S on
    presets = scene_set_presets("hard:4", 4)
    assert presets == ["gates", "blockers", "dense", "goals"]
    assert [figures.scene_label(twice, b, presets) for b in (1, 3)] == [
        "blockers scene 1, seed 1000001",
        "goals scene 3, seed 1000001",
    ]
    assert scene_set_presets("random:2", 2) == ["paper", "paper"] and scene_set_presets("x.json", 1) == [
        "file"
    ]


def test_trajectory_titles_name_the_preset_and_the_legend_the_goal_tolerance(pac_run, captured, tmp_path):
    scenes, rec = pac_run
    figures.plot_trajectories(rec, scenes, [0, 1], tmp_path / "t.png", presets=["gates", "dense"])
    (fig,) = captured
    titles = [ax.get_title() for ax in _panels(fig)]
    assert titles[0].startswith("gates scene 0, seed 1000000") and titles[1].startswith("dense scene 1")
    (legend,) = fig.legends
    assert f"goal tolerance ({FormationParams().goal_tolerance:g} m)" in [
        t.get_text() for t in legend.get_texts()
    ]


def test_collision_point_names_the_agent_whose_clearance_went_negative(mixed):
    scenes, rec = mixed
    assert list(rec.outcome) == [COLLISION, TIMEOUT]
    agent, point = figures.collision_point(rec, scenes, 0)
    last = rec.positions[0, rec.steps[0]]
    clear = agent_clearances(last[None], scenes.obstacles[:1])[0]
    assert clear[agent] < 0 and agent == int(np.argmin(clear))
    x, y, r = scenes.obstacles[0, 0]
    assert np.hypot(point[0] - x, point[1] - y) == pytest.approx(r)
    assert figures.collision_point(rec, scenes, 1) is None


def test_failure_grid_has_one_panel_per_failure_and_marks_the_collision(mixed, captured, tmp_path):
    scenes, rec = mixed
    figures.plot_failures(rec, scenes, tmp_path / "f.png", title="straight")
    (fig,) = captured
    panels = _panels(fig)
    assert len(fig.axes) == 2 and len(panels) == 2  # no empty panels
    _assert_labelled(fig)
    agent = FormationParams().graph.agents[figures.collision_point(rec, scenes, 0)[0]]
    assert panels[0].get_title().startswith(f"scene 0: collision ({agent})")
    assert agent in [t.get_text() for t in panels[0].texts]  # the agent named at the contact
    assert any(line.get_marker() == "X" for line in panels[0].lines)
    assert panels[1].get_title().startswith("scene 1: timeout")
    assert "2 of 2 failures shown (1 collision, 1 timeout" in fig._suptitle.get_text()
    assert (tmp_path / "f.png").stat().st_size > 0


def test_failure_grid_stops_at_nine(pac_run, captured, tmp_path):
    scenes, rec = pac_run
    idx = np.arange(12) % len(rec)
    many = dataclasses.replace(_take(rec, idx), outcome=np.full(12, TIMEOUT))
    figures.plot_failures(many, scenes[idx], tmp_path / "f.png")
    assert len(_panels(captured[0])) == 9
    assert "9 of 12 failures" in captured[0]._suptitle.get_text()


def test_trajectories_show_up_to_six_labelled_panels(pac_run, captured, tmp_path):
    scenes, rec = pac_run
    idx = np.arange(8) % len(rec)
    many = _take(rec, idx)
    figures.plot_trajectories(many, scenes[idx], range(8), tmp_path / "t.png", title="pac")
    (fig,) = captured
    assert len(_panels(fig)) == 6
    _assert_labelled(fig)
    assert _panels(fig)[0].get_title().startswith("scene 0, seed 1000000: success")


def test_histogram_title_gives_the_true_number_of_successful_runs(pac_run, captured, tmp_path):
    scenes, rec = pac_run
    many = _take(rec, np.arange(60) % len(rec))  # 60 successful runs: more than the old cap of 50
    many.outcome[:5] = COLLISION
    figures.plot_final_error_histogram(many, tmp_path / "h.png", title="pac")
    (fig,) = captured
    assert "55 successful runs (of 60 episodes)" in fig._suptitle.get_text()
    _assert_labelled(fig)
    assert sum(p.get_height() for p in fig.axes[0].patches) == 55
    # bins drawn with white edges, so two neighbours of one height stay two bars
    assert all(tuple(p.get_edgecolor()) == (1.0, 1.0, 1.0, 1.0) for ax in fig.axes[:2] for p in ax.patches)


def test_formation_errors_are_labelled_by_scene(pac_run, captured, tmp_path):
    scenes, rec = pac_run
    figures.plot_formation_errors(rec, [0, 1], tmp_path / "e.png", scenes=scenes)
    (fig,) = captured
    _assert_labelled(fig)
    (legend,) = fig.legends  # one for both panels
    assert [t.get_text() for t in legend.get_texts()] == ["scene 0, seed 1000000", "scene 1, seed 1000001"]
    # The velocity error is defined on the figure, with why it can exceed the leaders' speed cap.
    notes = " ".join(t.get_text() for t in fig.texts)
    assert "|v_i - v_i*|" in notes and "exceed the leaders' 0.6 m/s cap" in notes


def test_controllers_side_by_side_on_the_same_scenes(mixed, captured, tmp_path):
    scenes, straight = mixed
    records = {"pac": rollout(scenes, PACController(), max_steps=30), "straight": straight}
    shown = figures.comparison_scenes(records, 3)
    assert shown == [0, 1]  # only two scenes
    figures.plot_controller_comparison(records, scenes, shown, tmp_path / "c.png")
    (fig,) = captured
    panels = _panels(fig)
    assert len(panels) == 4
    _assert_labelled(fig)
    titles = [ax.get_title() for ax in panels]
    assert titles[0].startswith("pac, scene 0") and titles[1].startswith("straight, scene 0")
    assert titles[2].startswith("pac, scene 1") and titles[3].startswith("straight, scene 1")
    assert panels[0].get_xlim() == panels[1].get_xlim()  # one view per scene


def test_comparison_scenes_prefer_disagreement_but_keep_an_ordinary_one():
    def rec(outcome):
        return dataclasses.replace(_dummy(len(outcome)), outcome=np.array(outcome))

    records = {"a": rec([1, 1, 1, 2, 2]), "b": rec([1, 1, 1, 1, 1])}
    assert figures.comparison_scenes(records, 3) == [0, 3, 4]
    # every scene differs: two of them, then the next scene in order
    assert figures.comparison_scenes({"a": rec([1, 2, 2, 2]), "b": rec([2, 1, 1, 1])}, 3) == [0, 1, 2]


def _dummy(B: int) -> EpisodeRecords:
    params = FormationParams()
    pos = agent_positions(initial_state(np.zeros((B, 3)), params))
    z = np.zeros((B, 1))
    return EpisodeRecords(
        poses=np.zeros((B, 1, 3)),
        actions=np.zeros((B, 0, 2)),
        positions=pos[:, None],
        formation_error=z,
        follower_velocity_error=np.zeros((B, 0)),
        agent_clearance=z,
        midpoint_clearance=z,
        outcome=np.full(B, SUCCESS),
        steps=np.zeros(B, dtype=np.int64),
    )


def test_success_chart_error_bars_are_wilson_intervals(captured, tmp_path):
    assert figures.wilson_interval is metrics.wilson_interval  # reused, not rewritten
    counts = {
        "dataset scenes": {"pac": (10, 10), "diffusion": (7, 10)},
        "unseen scenes": {"diffusion": (0, 5)},
    }
    figures.plot_success_rates(counts, tmp_path / "s.png")
    (fig,) = captured
    (ax,) = fig.axes
    assert ax.get_ylabel() == "success rate [%]" and ax.get_xlabel() == "controller"
    bars = [c for c in ax.containers if isinstance(c, ErrorbarContainer)]
    spans = sorted(
        tuple(np.round(seg[:, 1], 6)) for bar in bars for seg in bar.lines[2][0].get_segments()
    )  # (low, high) of every error bar, in %
    want = sorted(
        tuple(np.round([100 * lo, 100 * hi], 6))
        for s, n in ((10, 10), (7, 10), (0, 5))
        for lo, hi in [metrics.wilson_interval(s, n)]
    )
    assert spans == want


def test_bench_writes_the_success_chart_and_lists_the_figures(tmp_path, capsys):
    from lerobot_formation.bench.cli import main

    assert (
        main(["--controllers", "pac", "--scenes", "random:2", "--out", str(tmp_path), "--no-progress"]) == 0
    )
    out = capsys.readouterr().out
    assert (tmp_path / "success_rates.png").stat().st_size > 1000
    assert "success_rates.png" in out and "pac_random_trajectories.png" in out
    assert not (tmp_path / "controllers_random.png").exists()  # one controller: nothing side by side


def test_success_chart_names_each_scene_set_by_what_it_is(captured, tmp_path):
    from lerobot_formation.bench.figures import write_success_figure
    from lerobot_formation.core.world.sampling import UNSEEN_SEED_START

    entry = {"success_rate": 0.5, "n_episodes": 4}
    results = {"random": {"diffusion": entry}, "unseen": {"diffusion": entry}}
    write_success_figure(tmp_path, results, {"random": "random:4", "unseen": "hard:4"}, UNSEEN_SEED_START)
    write_success_figure(tmp_path, results, {"random": "random:4", "unseen": "random:2"}, 0)
    legends = [[t.get_text() for t in fig.axes[0].get_legend().get_texts()] for fig in captured]
    assert legends == [
        [
            "paper-distribution scenes, unseen seeds (4 episodes)",
            "hard suite (gates, blockers, dense, other goals), unseen seeds (4 episodes)",
        ],
        # two sets of the same kind stay two entries, named by their specs
        [
            "paper-distribution scenes, seeds from 0 (4 episodes)",
            "paper-distribution scenes, seeds from 0 (random:2) (4 episodes)",
        ],
    ]
    assert figures.scene_set_label("dataset:100") == "dataset episodes' scenes"
    assert figures.scene_set_label("outputs/dagger/scenes.json") == "scenes of scenes.json"


def test_success_chart_says_not_run_where_a_controller_skipped_a_set(captured, tmp_path):
    figures.plot_success_rates(
        {"a": {"pac": (1, 2), "diffusion": (2, 2)}, "b": {"diffusion": (0, 2)}}, tmp_path / "s.png"
    )
    (fig,) = captured
    texts = [t.get_text() for t in fig.axes[0].texts]
    assert texts.count("not run") == 1  # pac on set b; diffusion's 0 % is a bar with its count
    assert "0 %\n0/2" in texts


def _with_conditions(rec: EpisodeRecords, scenes: Scenes) -> EpisodeRecords:
    """``rec`` as the engine records realistic conditions: obstacle 1 of each scene never sensed,
    obstacle 2 moving 0.03 m per step along +x (NaN after each episode's end)."""
    B, T1 = rec.poses.shape[:2]
    paths = np.repeat(scenes.obstacles[:, None, :, :2], T1, axis=1).copy()
    paths[:, :, 2, 0] += 0.03 * np.arange(T1)[None, :]
    paths[np.arange(T1)[None, :] > rec.steps[:, None]] = np.nan
    seen = np.zeros(scenes.mask.shape, dtype=np.int64)
    seen[:, 1] = -1
    return dataclasses.replace(rec, obstacle_paths=paths, seen_step=seen)


@pytest.fixture(scope="module")
def conditioned():
    scenes = scenes_from_list(
        [
            {"obstacles": [[0.5, 2.0, 0.4], [3.0, 3.0, 0.5], [-1.5, 1.0, 0.3]], "goal": [5.0, 5.0]},
            {"obstacles": [[2.0, 1.0, 0.3], [4.0, 1.0, 0.5], [-1.0, 3.0, 0.4]], "goal": [5.0, 5.0]},
        ],
        check=False,
    )
    rec = rollout(scenes, Straight(0.5), max_steps=30)
    return scenes, _with_conditions(rec, scenes)


def _legend_labels(fig) -> list[str]:
    return [t.get_text() for legend in fig.legends for t in legend.get_texts()]


def test_figures_show_the_sensed_map_and_moving_obstacles(conditioned, captured, tmp_path):
    scenes, rec = conditioned
    figures.plot_trajectories(rec, scenes, [0, 1], tmp_path / "t.png", title="sensed")
    figures.plot_failures(rec, scenes, tmp_path / "f.png")
    figures.plot_controller_comparison({"a": rec, "b": rec}, scenes, [0, 1], tmp_path / "c.png")
    assert all((tmp_path / f).stat().st_size > 1000 for f in ("t.png", "f.png", "c.png"))
    for fig in captured:
        labels = _legend_labels(fig)
        assert "obstacle never sensed" in labels and any(
            label.startswith("moving obstacle") for label in labels
        )
    ax = _panels(captured[0])[1]  # scene 1, ended by a timeout after 30 steps
    faint = [p for p in ax.patches if getattr(p, "get_alpha", lambda: None)() == 0.2]
    assert len(faint) == 1 and np.allclose(faint[0].center, (4.0, 1.0))  # the never-sensed obstacle
    moved = [line for line in ax.lines if line.get_linestyle() == ":"]
    assert len(moved) == 1 and np.isclose(moved[0].get_xdata()[-1], -1.0 + 0.03 * 30)
    # without conditions: no new legend entries
    plain = dataclasses.replace(rec, obstacle_paths=None, seen_step=None)
    figures.plot_trajectories(plain, scenes, [0, 1], tmp_path / "p.png")
    assert not {"obstacle never sensed"} & set(_legend_labels(captured[-1]))


def test_renderer_draws_unsensed_obstacles_faint_and_trails():
    from lerobot_formation.envs.render import COLORS, Renderer

    r = Renderer(size=100, bounds=(0.0, 10.0))
    obstacles = np.array([[2.0, 2.0, 0.5], [7.0, 7.0, 0.5]])
    positions = np.array([[5.0, 1.0], [5.5, 1.0], [5.0, 0.5], [5.5, 0.5]])
    edges = (np.array([0]), np.array([1]))
    trail = np.stack([np.c_[np.linspace(2.0, 2.0, 5), np.linspace(5.0, 4.0, 5)], np.full((5, 2), np.nan)], 1)
    img = r.draw(
        obstacles, (9.0, 1.0), positions, edges, sensed=np.array([True, False]), obstacle_trails=trail
    )
    pixel = lambda x, y: tuple(img[r._to_pixel(np.array([x, y]))])  # noqa: E731
    assert pixel(2.0, 2.0) == COLORS["obstacle"]
    assert pixel(7.0, 7.0) == COLORS["obstacle_unsensed"]
    assert pixel(2.0, 4.5) == COLORS["obstacle_trail"]
    plain = r.draw(obstacles, (9.0, 1.0), positions, edges)
    assert tuple(plain[r._to_pixel(np.array([7.0, 7.0]))]) == COLORS["obstacle"]
