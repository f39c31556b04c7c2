"""lerobot-formation-bench: results.json keys, tables, figures and bad arguments."""

import dataclasses
import json

import numpy as np
import pytest

from lerobot_formation.bench.cli import main
from lerobot_formation.bench.scene_sets import parse_scenes
from lerobot_formation.core.world.sampling import sample_scenes
from lerobot_formation.core.world.scene_files import save_scenes


def test_bench_pac_and_mppi_write_results_tables_and_figures(tmp_path):
    assert (
        main(["--controllers", "pac,mppi", "--scenes", "random:3", "--out", str(tmp_path), "--no-progress"])
        == 0
    )
    res = json.loads((tmp_path / "results.json").read_text())
    for name in ("pac", "mppi"):
        r = res[name]
        assert {"success_rate", "n_episodes", "collisions", "timeouts", "episodes", "success_ci95"} <= set(r)
        assert r["n_episodes"] == 3 and 0 <= r["success_rate"] <= 1
        assert len(r["episodes"]) == 3 and {"seed", "outcome", "steps", "path_length"} <= set(
            r["episodes"][0]
        )
        assert (tmp_path / f"{name}_random_trajectories.png").stat().st_size > 1000
        assert (tmp_path / f"{name}_random_formation_error.png").is_file()
    assert res["meta"]["scene_sampling"]["accepted"] == 3
    tables = (tmp_path / "tables.md").read_text()
    assert "| Success Rate (%) |" in tables and "65.0" in tables  # the paper's MPPI beside ours
    # Our clearance sits beside the paper's: the table says what ours measures and that the paper's may differ.
    assert "midpoint to the nearest obstacle surface" in tables and "does not define" in tables


def test_jobs_run_controllers_side_by_side_with_the_numbers_of_one_by_one(tmp_path, capsys):
    """--jobs 2: each controller whole in a forked process; the same episodes, in the order asked for,
    and the records come back for the figures."""
    common = ["--controllers", "route-pursuit,pac,mppi", "--scenes", "level5:1", "--no-progress"]
    assert main([*common, "--out", str(tmp_path / "one"), "--no-figures"]) == 0
    assert main([*common, "--out", str(tmp_path / "two"), "--jobs", "2"]) == 0
    one, two = (
        json.loads((tmp_path / d / "results.json").read_text())["by_scenes"]["level5"] for d in ("one", "two")
    )
    assert list(two) == ["route-pursuit", "pac", "mppi"]
    for name in one:
        assert one[name]["episodes"] == two[name]["episodes"]
    assert (tmp_path / "two" / "mppi_level5_trajectories.png").is_file()
    with pytest.raises(SystemExit):
        main([*common, "--out", str(tmp_path / "bad"), "--jobs", "0"])
    assert "--jobs must be >= 1, got 0" in capsys.readouterr().err


def test_scenes_file_and_dataset_spec(tmp_path):
    save_scenes(sample_scenes([7, 8]), tmp_path / "s.json")
    assert len(parse_scenes(str(tmp_path / "s.json"), 0)) == 2
    with pytest.raises(ValueError, match="dataset:N needs"):
        parse_scenes("dataset:5", 0)
    with pytest.raises(ValueError, match="integer N"):
        parse_scenes("random:x", 0)


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["--controllers", "pac,foo"], "unknown controller 'foo'"),
        (["--controllers", "diffusion"], "need --policy.path"),
        (["--scenes", "random:0"], "N >= 1"),
        (["--controllers", "diffusion", "--policy.path", "m", "--device", "gpu0"], "got 'gpu0'"),
        (["--controllers", "diffusion", "--policy.path", "m", "--device", "mps"], "cpu or a CUDA device"),
    ],
)
def test_bad_arguments(argv, match, capsys, tmp_path):
    with pytest.raises(SystemExit):
        main([*argv, "--out", str(tmp_path)])
    assert match in capsys.readouterr().err


def test_cuda_device_without_cuda_is_named(capsys, tmp_path):
    torch = pytest.importorskip("torch")
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    with pytest.raises(SystemExit):
        main(["--controllers", "diffusion", "--policy.path", "m", "--device", "cuda", "--out", str(tmp_path)])
    assert "CUDA is not available on this machine" in capsys.readouterr().err


def test_bench_runs_the_privileged_expert_on_the_true_world():
    """``pac-privileged`` in the bench acts on the true world: under sensing noise and a 3 m
    sensing range (which change only what the team perceives) its episodes are those it drives with
    no conditions at all, while plain PAC's change."""
    from lerobot_formation.bench.controllers import make_controller
    from lerobot_formation.bench.evaluation import evaluate
    from lerobot_formation.bench.settings import ControllerOptions
    from lerobot_formation.core.perception.conditions import Conditions
    from lerobot_formation.core.world.dynamics import FormationParams
    from lerobot_formation.core.world.sampling import sample_scenes

    scenes, params = sample_scenes(range(3)), dataclasses.replace(FormationParams(), max_steps=150)
    sensing = Conditions(sensing_range=3.0, obstacle_noise=0.1, pose_noise=0.05)
    runs = {}
    for name in ("pac", "pac-privileged"):
        for label, cond in (("exact", None), ("sensing", sensing)):
            controller = make_controller(name, params, ControllerOptions(conditions=cond))
            runs[name, label] = evaluate(controller, scenes, params, conditions=cond)
    same = runs["pac-privileged", "sensing"].poses, runs["pac-privileged", "exact"].poses
    np.testing.assert_array_equal(*same)
    assert not np.array_equal(runs["pac", "sensing"].poses, runs["pac", "exact"].poses, equal_nan=True)
