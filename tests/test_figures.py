"""Figures: labelled axes, real scene names, true counts, failure grids with the collision marked,
controllers side by side and the success chart's Wilson intervals."""

import dataclasses

import numpy as np
import pytest
from matplotlib.container import ErrorbarContainer

from lerobot_formation.bench.plots import figures
from lerobot_formation.core import metrics
from lerobot_formation.core.dynamics import FormationParams, agent_positions, initial_state
from lerobot_formation.core.geometry import agent_clearances
from lerobot_formation.core.rollout import COLLISION, SUCCESS, TIMEOUT, EpisodeRecords, PACController, rollout
from lerobot_formation.core.scene import Scenes, sample_scenes, scenes_from_list

PAPER_START = [0.0, 0.0, np.pi / 2]  # midpoint at the origin, heading +y


class Straight:
    """Drives the midpoint straight ahead at ``v`` m/s (0: stands still, a timeout)."""

    name = "straight"

    def __init__(self, v: float):
        self.v = v

    def reset(self, scenes) -> None:
        pass

    def act(self, state, idx):
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
    return EpisodeRecords(
        **{f.name: getattr(rec, f.name)[idx] if f.name != "dt" else rec.dt for f in dataclasses.fields(rec)}
    )


def _panels(fig):
    return [ax for ax in fig.axes if ax.axison]


def _assert_labelled(fig):
    """Both axes labelled, x with its unit (a y axis of counts, "episodes", has none)."""
    for ax in _panels(fig):
        assert "[" in ax.get_xlabel() and ax.get_ylabel(), (ax.get_xlabel(), ax.get_ylabel())


def test_scene_label_is_the_seed_or_the_index_in_the_scene_set(mixed, pac_run):
    assert figures.scene_label(mixed[0], 1) == "scene 1"
    assert figures.scene_label(pac_run[0], 2) == "seed 1000002"
    twice = Scenes.concat([pac_run[0][:2], pac_run[0][:2]])  # the hard suite: each preset from seed S on
    assert [figures.scene_label(twice, b) for b in (1, 3)] == [
        "scene 1, seed 1000001",
        "scene 3, seed 1000001",
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
    assert _panels(fig)[0].get_title().startswith("scene 0, seed 1000000: success")  # scenes repeat


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
    assert [t.get_text() for t in legend.get_texts()] == ["seed 1000000", "seed 1000001"]


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
    from lerobot_formation.bench.cli import write_success_figure
    from lerobot_formation.core.scene import UNSEEN_SEED_START

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
