"""Issue 11: every bad input a clear error, every interruption loses nothing.

One test (or a few) per case of the issue: killed generations, scenes with more obstacles than the
observation encodes, concurrent generations, metrics of obstacle-free scenes, far goals, malformed
scene files, bad checkpoints and bench arguments, env misuse, start-up checks of lerobot-train, and
the run id of the formation-metrics JSONL.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import last_error_line, standard_policy_kwargs, stock_diffusion_checkpoint, tiny_diffusion_kwargs

from datasets_scripts import generate_pac_dataset as gen_mod
from lerobot_formation.bench.cli import main as bench_main
from lerobot_formation.bench.scene_sets import parse_scenes
from lerobot_formation.core.world.navigation import cost_to_go
from lerobot_formation.core.world.presets import SceneConfig
from lerobot_formation.core.world.sampling import sample_scenes
from lerobot_formation.core.world.scene_files import load_scenes, scenes_from_list
from lerobot_formation.data import lerobot_writer
from lerobot_formation.data.safe_destination import remove_stale_temporaries, rename_noreplace
from lerobot_formation.envs.env import FormationEnv
from lerobot_formation.envs.vector_env import FormationVectorEnv

ROOT = Path(__file__).resolve().parents[1]
CHECKPOINT = ROOT / "pretrained" / "formation_diffusion_cpu"
EMPTY_NEAR_GOAL = {"obstacles": [], "goal": [0.0, 0.5]}  # reached in a few steps straight ahead

# Seven obstacles well off the start-goal diagonal: PAC solves it, the grid encodes at most 49 cells.
SEVEN = [[3.5, 0.5, 0.3], [5.5, 1.5, 0.3], [0.5, 3.5, 0.3], [1.5, 5.5, 0.3], [6.5, 3.0, 0.3], [3.0, 6.5, 0.3]]
SEVEN.append([-1.5, 2.0, 0.3])


def write_scenes(path: Path, scenes: list[dict]) -> Path:
    path.write_text(json.dumps({"scenes": scenes}))
    return path


# -- lerobot-formation-generate: killed runs, concurrent runs ----------------------------------------
def _start_generation(root: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "datasets_scripts.generate_pac_dataset", "--episodes", "400"]
    cmd += [
        "--batch-size",
        "2",  # the first episodes written soon
        "--workers",
        "1",
        "--root",
        str(root),
        "--repo-id",
        "local/kill",
        "--no-progress",
    ]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    return subprocess.Popen(
        cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )


def _wait_until_writing(proc: subprocess.Popen, root: Path, timeout: float = 90.0):
    """The generation's worker processes once its temporary folder holds a parquet file."""
    psutil = pytest.importorskip("psutil")
    t0 = time.time()
    while time.time() - t0 < timeout:
        assert proc.poll() is None, proc.stderr.read()
        workers = psutil.Process(proc.pid).children(recursive=True)
        tmps = list(root.parent.glob(f".{root.name}.tmp-*"))
        if workers and tmps and any(tmps[0].rglob("*.parquet")):
            return workers
        time.sleep(0.2)
    raise AssertionError("the generation did not start writing in time")


def _alive(procs, timeout: float = 5.0) -> list[int]:
    """The pids of ``procs`` still running after up to ``timeout`` s (polled: no fixed sleep)."""
    import psutil

    deadline = time.monotonic() + timeout
    while True:
        out = []
        for p in procs:
            try:
                if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                    out.append(p.pid)
            except psutil.NoSuchProcess:
                pass
        if not out or time.monotonic() > deadline:
            return out
        time.sleep(0.1)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="signals and /proc as on Linux")
def test_killed_generation_leaves_no_worker_and_a_rerun_no_temporary_folder(tmp_path):
    root = tmp_path / "ds"
    # SIGTERM: the handler raises SystemExit, so the cleanup runs at once
    proc = _start_generation(root)
    workers = _wait_until_writing(proc, root)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(30) == 128 + signal.SIGTERM
    assert _alive(workers) == []
    assert list(tmp_path.iterdir()) == []  # no temporary folder, no destination
    assert "Traceback" not in proc.stderr.read()
    # SIGKILL: no cleanup can run; the workers die with the parent, the rerun removes the folder
    proc = _start_generation(root)
    workers = _wait_until_writing(proc, root)
    proc.kill()
    proc.wait(30)
    assert _alive(workers) == []
    stale = list(tmp_path.glob(".ds.tmp-*"))
    assert len(stale) == 1
    assert gen_mod.main(["--episodes", "2", "--workers", "0", "--root", str(root), "--no-progress"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]


def test_second_generation_into_the_same_root_fails(tmp_path, capsys):
    root = tmp_path / "ds"
    argv = ["--episodes", "2", "--workers", "0", "--root", str(root), "--no-progress"]
    assert gen_mod.main(argv) == 0
    info = (root / "meta" / "info.json").read_text()
    assert gen_mod.main(argv) == 2
    assert f"error: destination {root} already exists; pass --overwrite" in capsys.readouterr().err
    assert (root / "meta" / "info.json").read_text() == info


def test_generation_refuses_a_destination_that_appeared_meanwhile(tmp_path, monkeypatch):
    root = tmp_path / "ds"
    write = lerobot_writer.write_episode

    def write_then_appear(ds, frames, fast=True):  # another run finishes first
        write(ds, frames, fast)
        root.mkdir(exist_ok=True)
        (root / "theirs.txt").write_text("the other run's dataset")

    monkeypatch.setattr(lerobot_writer, "write_episode", write_then_appear)
    with pytest.raises(FileExistsError, match="appeared while this run was generating.*--overwrite"):
        lerobot_writer.generate(root, "local/x", 2, workers=0, progress=False)
    assert sorted(p.name for p in root.iterdir()) == ["theirs.txt"]  # not replaced
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]  # our temporary folder removed


def test_rename_never_replaces_even_an_empty_folder(tmp_path):
    (tmp_path / "src").mkdir()
    (tmp_path / "dst").mkdir()  # os.rename would silently replace it
    with pytest.raises(FileExistsError):
        rename_noreplace(tmp_path / "src", tmp_path / "dst")
    assert (tmp_path / "src").is_dir()


def test_live_writer_refused_stale_temporaries_removed(tmp_path):
    root = tmp_path / "ds"
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (tmp_path / f".ds.tmp-{sleeper.pid}").mkdir()
        with pytest.raises(FileExistsError, match=f"another generation \\(pid {sleeper.pid}\\) is writing"):
            lerobot_writer.generate(root, "local/x", 2, workers=0, progress=False)
    finally:
        sleeper.kill()
        sleeper.wait()
    # now that process is gone: its folder is stale, and a .old- one of a dead run too
    (tmp_path / f".ds.old-{sleeper.pid}").mkdir()
    removed = remove_stale_temporaries(root)
    assert sorted(p.name for p in removed) == [f".ds.old-{sleeper.pid}", f".ds.tmp-{sleeper.pid}"]
    assert list(tmp_path.iterdir()) == []


def test_more_episodes_than_the_scenes_file_holds(tmp_path, capsys):
    f = write_scenes(tmp_path / "s.json", sample_scenes([1, 2]).to_list())
    argv = [
        "--scenes",
        str(f),
        "--episodes",
        "3",
        "--workers",
        "0",
        "--root",
        str(tmp_path / "ds"),
        "--no-progress",
    ]
    assert gen_mod.main(argv) == 2
    assert last_error_line(capsys.readouterr().err) == (
        f"error: --episodes 3 asks for more episodes than scenes file {f} holds (2 scenes)"
    )
    assert not (tmp_path / "ds").exists()


# -- scenes carry every obstacle ---------------------------------------------------------------------
def test_seven_obstacles_in_the_grid_encoding_round_trip_through_dataset_n(tmp_path):
    scenes = [{"obstacles": SEVEN, "goal": [5.0, 5.0]}, {"obstacles": SEVEN[:6], "goal": [5.0, 4.5]}]
    f = write_scenes(tmp_path / "s.json", scenes)
    root = tmp_path / "ds"
    argv = ["--scenes", str(f), "--episodes", "2", "--obstacle-encoding", "grid", "--workers", "0"]
    assert gen_mod.main([*argv, "--root", str(root), "--no-progress"]) == 0
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["features"]["scene.obstacles"]["shape"] == [21]  # 7 slots, not the observation's 5
    back = parse_scenes("dataset:2", 0, dataset_root=str(root))
    want = load_scenes(f)
    for b in range(2):
        np.testing.assert_allclose(
            back.obstacles[b][back.mask[b]], want.obstacles[b][want.mask[b]], atol=1e-6
        )
        np.testing.assert_allclose(back.goal[b], want.goal[b], atol=1e-6)
        np.testing.assert_allclose(back.start[b], want.start[b], atol=1e-6)
    assert back.mask.sum(axis=1).tolist() == [7, 6]
    with pytest.raises(ValueError, match="fewer than the 3 asked for"):
        parse_scenes("dataset:3", 0, dataset_root=str(root))
    out = tmp_path / "bench"  # the same scenes through the bench's command line
    argv = ["--controllers", "pac", "--scenes", "dataset:2", "--dataset.root", str(root), "--out", str(out)]
    assert bench_main([*argv, "--no-figures", "--no-progress"]) == 0
    assert json.loads((out / "results.json").read_text())["pac"]["success_rate"] == 1.0


# -- metrics of a scene with no obstacle -------------------------------------------------------------
def test_min_clearance_without_obstacles_is_null(tmp_path):
    f = write_scenes(tmp_path / "empty.json", [{"obstacles": [], "goal": [0.0, 3.0]}])
    out = tmp_path / "out"
    assert (
        bench_main(
            ["--controllers", "pac", "--scenes", str(f), "--out", str(out), "--no-figures", "--no-progress"]
        )
        == 0
    )
    res = json.loads((out / "results.json").read_text())
    ep = res["pac"]["episodes"][0]
    assert ep["outcome"] == "success"
    for key in ("min_clearance", "mean_clearance", "formation_min_clearance"):
        assert ep[key] is None
        assert res["pac"][key] == {"mean": None, "std": None}
    assert "1414" not in (out / "results.json").read_text()
    assert "| Min Clearance (m) | n/a |" in (out / "tables.md").read_text()


def test_env_info_clearance_without_obstacles_is_none():
    env = FormationEnv()
    _, info = env.reset(options={"scene": {"obstacles": [], "goal": [0.0, 3.0]}})
    assert info["clearance"] is None and info["midpoint_clearance"] is None
    _, _, _, _, info = env.step(np.array([0.3, 0.0], np.float32))
    assert info["clearance"] is None and info["midpoint_clearance"] is None
    _, info = env.reset(options={"scene": {"obstacles": [[3, 3, 0.5]], "goal": [5, 5]}})
    assert 3.0 < info["midpoint_clearance"] < 4.0
    venv = FormationVectorEnv(2)
    empty = scenes_from_list(
        [{"obstacles": [], "goal": [0.0, 3.0]}, {"obstacles": [[3, 3, 0.5]], "goal": [5, 5]}]
    )
    _, vinfo = venv.reset(options={"scenes": empty})
    assert np.isnan(vinfo["midpoint_clearance"][0]) and np.isfinite(vinfo["midpoint_clearance"][1])


# -- far goals ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("x", [300.0, 1e5])
def test_far_goal_is_refused(x, tmp_path, capsys):
    """Refused by each entry point before any work (how fast: benchmarks/bench_refusals.py)."""
    with pytest.raises(ValueError, match=f"is {x:.1f} m from the start .* at most 50 m is supported"):
        scenes_from_list([{"obstacles": [], "goal": [x, 0.0]}])
    with pytest.raises(ValueError, match="more than 600 cells"):
        cost_to_go(np.zeros((1, 1, 3)), np.array([[x, 0.0]]))
    with pytest.raises(ValueError, match="at most 50 m"):
        SceneConfig(goal=(x, 0.0))
    f = write_scenes(tmp_path / "far.json", [{"obstacles": [], "goal": [x, 0.0]}])
    with pytest.raises(SystemExit) as e:
        bench_main(
            ["--controllers", "pac", "--scenes", str(f), "--out", str(tmp_path / "o"), "--no-progress"]
        )
    assert e.value.code == 2
    line = last_error_line(capsys.readouterr().err)
    assert line.startswith(f"error: scenes file {f}: scene 0: goal [{x}, 0.0] is")


# -- scene files -------------------------------------------------------------------------------------
RING = [[5 + 1.6 * np.cos(a), 5 + 1.6 * np.sin(a), 0.8] for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]


@pytest.mark.parametrize(
    ("scenes", "message"),
    [
        (
            [{"obstacles": [["3", 3, 0.5]], "goal": [5, 5]}],
            "scene 0: obstacles must be [[x, y, r], ...]; obstacle 0 must be [x, y, r] (numbers), got ['3', 3, 0.5]",
        ),
        (
            [{"obstacles": [[3, 3, True]], "goal": [5, 5]}],
            "scene 0: obstacles must be [[x, y, r], ...]; obstacle 0 must be [x, y, r] (numbers), got [3, 3, True]",
        ),
        ([{"obstacles": [], "goal": ["5", 5]}], "scene 0: goal must be [x, y] (numbers), got ['5', 5]"),
        (
            [{"obstacles": [], "goal": [5, 5], "start": [0, 0, False]}],
            "scene 0: start must be [x, y, phi] (numbers), got [0, 0, False]",
        ),
        (
            [{"obstacles": [], "goal": [5, 5], "goall": [5, 5]}],
            "scene 0: unknown key 'goall'; allowed keys: 'obstacles', 'goal', 'start'",
        ),
        (
            [{"obstacles": None, "goal": [5, 5]}],
            "scene 0: obstacles must be a list [[x, y, r], ...], got None",
        ),
        (
            [{"obstacles": {"x": 1}, "goal": [5, 5]}],
            "scene 0: obstacles must be a list [[x, y, r], ...], got {'x': 1}",
        ),
        ([{"obstacles": [], "goal": None}], "scene 0: goal must be [x, y] (numbers), got None"),
        (None, "expected a non-empty list of scenes, got NoneType None"),
        ({"obstacles": []}, "expected a non-empty list of scenes, got dict {'obstacles': []}"),
        ([None], "scene 0 must be a dict with keys 'obstacles' and 'goal', got None"),
        (
            [{"obstacles": [], "goal": [5, 5]}, {"obstacles": RING, "goal": [5, 5]}],
            "scene 1: no passage from the start [0.0, 0.0] to the goal [5.0, 5.0]",
        ),
    ],
)
def test_malformed_scene_files_name_file_and_scene(tmp_path, scenes, message):
    f = tmp_path / "s.json"
    f.write_text(json.dumps({"scenes": scenes}))
    with pytest.raises(ValueError) as e:
        load_scenes(f)
    assert str(e.value).startswith(f"scenes file {f}: {message}")


def test_walled_off_goal_is_refused_by_the_env_too():
    with pytest.raises(ValueError, match="no passage"):
        FormationEnv().reset(options={"scene": {"obstacles": RING, "goal": [5, 5]}})


# -- the bench: checkpoints and arguments ------------------------------------------------------------
def _broken_checkpoint(tmp_path: Path, kind: str) -> Path:
    if kind == "missing":
        return tmp_path / "no_such_checkpoint"
    if kind == "stock":
        return stock_diffusion_checkpoint(tmp_path / "stock")
    if not CHECKPOINT.is_dir():
        pytest.skip("no pretrained checkpoint")
    path = tmp_path / kind
    shutil.copytree(CHECKPOINT, path)
    if kind == "truncated":
        data = (path / "model.safetensors").read_bytes()
        (path / "model.safetensors").write_bytes(data[: len(data) // 2])
    elif kind == "broken_config":
        (path / "config.json").write_text('{"type": "formation_diffusion", ')
    elif kind == "bad_field":
        cfg = json.loads((path / "config.json").read_text())
        cfg["horizon"] = "sixteen"
        (path / "config.json").write_text(json.dumps(cfg))
    elif kind == "inconsistent":  # each field valid, the config's own check refuses the pair
        cfg = json.loads((path / "config.json").read_text())
        cfg["drop_n_last_frames"] = 3
        (path / "config.json").write_text(json.dumps(cfg))
    return path


@pytest.mark.parametrize(
    ("kind", "message"),
    [
        ("missing", "error: --policy.path: policy checkpoint folder {p} does not exist"),
        ("truncated", "error: --policy.path: {p}/model.safetensors cannot be loaded (truncated?)"),
        ("broken_config", "error: --policy.path: {p}/config.json is not valid JSON"),
        ("bad_field", "error: --policy.path: {p}/config.json is not a valid formation_diffusion config"),
        (
            "inconsistent",
            "error: --policy.path: {p}/config.json is not a valid formation_diffusion config: "
            "drop_n_last_frames=3 does not match",
        ),
        ("stock", "error: --policy.path: {p} holds a policy of type 'diffusion', not 'formation_diffusion'"),
    ],
)
def test_bad_policy_path_is_one_error_line(tmp_path, capsys, kind, message):
    path = _broken_checkpoint(tmp_path, kind)
    with pytest.raises(SystemExit) as e:
        bench_main(
            [
                "--controllers",
                "diffusion",
                "--policy.path",
                str(path),
                "--scenes",
                "random:1",
                "--out",
                str(tmp_path / "o"),
            ]
        )
    assert e.value.code == 2
    assert last_error_line(capsys.readouterr().err).startswith(message.format(p=path))


@pytest.mark.parametrize(("steps", "message"), [("0", "must be >= 1, got 0"), ("-3", "must be >= 1, got -3")])
def test_bad_inference_steps(tmp_path, capsys, steps, message):
    argv = ["--controllers", "diffusion", "--policy.path", str(CHECKPOINT), "--num-inference-steps", steps]
    with pytest.raises(SystemExit) as e:
        bench_main([*argv, "--scenes", "random:1", "--out", str(tmp_path)])
    assert e.value.code == 2
    assert last_error_line(capsys.readouterr().err) == f"error: --num-inference-steps {message}"


def test_failing_controller_keeps_the_finished_results(tmp_path, capsys):
    if not CHECKPOINT.is_dir():
        pytest.skip("no pretrained checkpoint")
    out = tmp_path / "o"
    argv = ["--controllers", "pac,diffusion-safe", "--policy.path", str(CHECKPOINT), "--scenes", "random:2"]
    with pytest.raises(SystemExit) as e:
        bench_main([*argv, "--out", str(out), "--no-figures", "--no-progress"])
    assert e.value.code == 2
    assert last_error_line(capsys.readouterr().err).startswith(
        "error: controller diffusion-safe: the safety layer (num_candidates=10, safety_filter='cbf', "
        "sampling_guidance=0.0) needs an egocentric"
    )
    res = json.loads((out / "results.json").read_text())
    assert res["pac"]["n_episodes"] == 2 and "diffusion-safe" not in res
    assert res["meta"]["incomplete"] is True and "diffusion-safe" in res["meta"]["error"]
    assert "Incomplete run" in (out / "tables.md").read_text()


# -- the env -----------------------------------------------------------------------------------------
def test_step_after_the_episode_ended_raises():
    env = FormationEnv()
    env.reset(options={"scene": EMPTY_NEAR_GOAL})
    for _ in range(20):
        _, _, terminated, _, info = env.step(np.array([0.6, 0.0], np.float32))
        if terminated:
            break
    assert terminated and info["is_success"]
    with pytest.raises(RuntimeError, match=r"the episode has ended \(success at step \d+\); call reset\(\)"):
        env.step(np.array([0.6, 0.0], np.float32))
    env.reset(seed=0)
    env.step(np.array([0.6, 0.0], np.float32))  # fine again after reset


def test_lerobot_wrapper_stack_replays_after_the_end(tmp_path):
    """LeRobot's FreezeAfterEpisodeEnd keeps stepping finished sub-envs: it must not reach the env."""
    from lerobot_formation.envs.env_config import FormationEnvConfig

    f = write_scenes(tmp_path / "s.json", [EMPTY_NEAR_GOAL])
    env = FormationEnvConfig(scenes_file=str(f), episode_length=20).make_env_factory()()
    env.reset(seed=0)
    ends = [env.step(np.array([0.6, 0.0], np.float32))[2] for _ in range(10)]
    assert ends[-1] and sum(ends) >= 2  # terminated, then replayed


def test_reset_options_and_render_size():
    with pytest.raises(ValueError, match=r"options must be a dict or None, got list \[1\]"):
        FormationEnv().reset(options=[1])
    for size in (0, -5, 1.5, True, 10_000):
        with pytest.raises(ValueError, match="render_size must be an int in \\[8, 2048\\]"):
            FormationEnv(render_mode="rgb_array", render_size=size)
    FormationEnv().reset(options={"lerobot_new_rollout": True})  # LeRobot's own option is fine


def test_seed_past_the_end_of_a_scenes_file(tmp_path):
    f = write_scenes(tmp_path / "s.json", sample_scenes([1, 2, 3]).to_list())
    env = FormationEnv(scenes_file=str(f))
    env.reset(seed=2)
    for seed in (3, 1000, -1):
        with pytest.raises(
            ValueError,
            match=f"seed {seed} is past the end of scenes file .* \\(3 scenes, seeds 0..2\\).*--seed=0",
        ):
            env.reset(seed=seed)
    venv = FormationVectorEnv(2, scenes_file=str(f))
    venv.reset(seed=1)  # seeds 1, 2
    with pytest.raises(ValueError, match="seed 3 is past the end"):
        venv.reset(seed=2)  # seeds 2, 3
    venv.reset()  # random scenes of the file
    assert set(venv.scenes.seeds.tolist()) <= {-1}


# -- lerobot-train start-up checks -------------------------------------------------------------------
def test_env_encoding_that_does_not_fit_the_policy_fails_at_start_up(tmp_path):
    """lerobot-train validates its config, builds the policy, then calls make_env_pre_post_processors(env_cfg,
    policy_cfg) before its first step; lerobot-eval's config loads the policy config and the same call
    comes before the first episode. Both pipeline configs hand our env config the policy config: an
    env given no encoding takes the policy's, one given another is refused naming both."""
    from lerobot.configs.default import DatasetConfig
    from lerobot.configs.eval import EvalPipelineConfig
    from lerobot.configs.train import TrainPipelineConfig
    from lerobot.envs.factory import make_env_pre_post_processors

    from lerobot_formation.envs.env_config import FormationEnvConfig, check_policy_features
    from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig

    policy_cfg = FormationDiffusionConfig(**tiny_diffusion_kwargs(66), **standard_policy_kwargs(66))

    def train(encoding: str | None) -> TrainPipelineConfig:
        env = FormationEnvConfig(obstacle_encoding=encoding)
        cfg = TrainPipelineConfig(
            dataset=DatasetConfig(repo_id="local/x", root=str(tmp_path)), env=env, policy=policy_cfg
        )
        cfg.validate()
        return cfg

    def evaluate(encoding: str | None) -> EvalPipelineConfig:
        return EvalPipelineConfig(env=FormationEnvConfig(obstacle_encoding=encoding), policy=policy_cfg)

    for pipeline in (train("grid+list"), evaluate("grid+list"), train(None), evaluate(None)):
        assert pipeline.env.run_policy is policy_cfg and pipeline.env.obstacle_encoding == "grid+list"
        make_env_pre_post_processors(pipeline.env, pipeline.policy)
    for build in (train, evaluate):
        with pytest.raises(ValueError) as e:
            build("grid")
        assert str(e.value) == (
            "--env.obstacle_encoding=grid differs from the policy's obstacle_encoding=grid+list: drop "
            "--env.obstacle_encoding (the env then observes the policy's) or pass --env.obstacle_encoding=grid+list"
        )
    with pytest.raises(ValueError) as e:  # the processors' check, where the sizes differ
        check_policy_features(FormationEnvConfig(obstacle_encoding="grid"), policy_cfg)
    assert str(e.value) == (
        "--env.obstacle_encoding=grid gives 'observation.environment_state' 51 values, but the policy takes "
        "66 (its dataset or checkpoint uses 'grid+list'): pass --env.obstacle_encoding=grid+list"
    )


def test_env_encoding_of_the_same_size_but_another_route_hint_fails_at_start_up():
    """``nearest+route`` and ``nearest+maproute`` both give 55 values: the name, not the size, decides."""
    from lerobot.configs.eval import EvalPipelineConfig
    from lerobot.envs.factory import make_env_pre_post_processors

    from lerobot_formation.envs.env_config import FormationEnvConfig, check_policy_features
    from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig

    policy_cfg = FormationDiffusionConfig(
        **tiny_diffusion_kwargs(55), **{**standard_policy_kwargs(55), "obstacle_encoding": "nearest+maproute"}
    )
    same = EvalPipelineConfig(env=FormationEnvConfig(obstacle_encoding="nearest+maproute"), policy=policy_cfg)
    make_env_pre_post_processors(same.env, same.policy)
    with pytest.raises(ValueError) as e:
        EvalPipelineConfig(env=FormationEnvConfig(obstacle_encoding="nearest+route"), policy=policy_cfg)
    assert (
        "--env.obstacle_encoding=nearest+route differs from the policy's obstacle_encoding=nearest+maproute"
        in str(e.value)
    )
    with pytest.raises(ValueError) as e:  # the processors' check of the same
        check_policy_features(FormationEnvConfig(obstacle_encoding="nearest+route"), policy_cfg)
    assert str(e.value) == (
        "--env.obstacle_encoding=nearest+route gives 'observation.environment_state' the size the policy "
        "takes, but the policy observes 'nearest+maproute': pass --env.obstacle_encoding=nearest+maproute"
    )


def test_missing_dataset_root_offline_is_a_clear_error(tmp_path, monkeypatch):
    """lerobot-train refuses it when it validates its config (our config installed the check)."""
    from huggingface_hub import constants
    from lerobot.configs.default import DatasetConfig
    from lerobot.configs.train import TrainPipelineConfig

    from lerobot_formation.compat.run_checks import ConfigError
    from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig

    def validate(root: Path) -> None:
        policy = FormationDiffusionConfig(**tiny_diffusion_kwargs(66), **standard_policy_kwargs(66))
        TrainPipelineConfig(
            dataset=DatasetConfig(repo_id="local/x", root=str(root)), policy=policy
        ).validate()

    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    missing = tmp_path / "no_dataset"
    with pytest.raises(
        ConfigError, match=f"--dataset.root {missing} does not exist, and HF_HUB_OFFLINE is set"
    ):
        validate(missing)
    assert not missing.exists()
    validate(tmp_path)  # an existing root is fine
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", False)
    validate(missing)  # online: LeRobot downloads there


def test_env_scenes_file_is_checked_at_start_up(tmp_path):
    from lerobot_formation.envs.env_config import FormationEnvConfig

    with pytest.raises(ValueError, match="env.scenes_file: scenes file .* does not exist"):
        FormationEnvConfig(scenes_file=str(tmp_path / "nope.json"))


# -- the formation-metrics JSONL ---------------------------------------------------------------------
def test_jsonl_lines_carry_run_id_and_episode_index(tmp_path):
    from lerobot_formation.envs.env_config import FormationEnvConfig

    f = write_scenes(tmp_path / "s.json", [EMPTY_NEAR_GOAL, EMPTY_NEAR_GOAL])
    log = tmp_path / "m.jsonl"
    for _run in range(2):  # two runs append to the same file
        cfg = FormationEnvConfig(scenes_file=str(f), episode_length=20, episode_metrics_path=str(log))
        vec = cfg.create_envs(2)["formation"][0]
        for _episode in range(2):
            vec.reset(seed=0, options={"lerobot_new_rollout": True})
            for _ in range(12):
                vec.step(np.tile([0.6, 0.0], (2, 1)).astype(np.float32))
        vec.close()
    lines = [json.loads(ln) for ln in log.read_text().splitlines()]
    assert len(lines) == 8
    runs = sorted({ln["run_id"] for ln in lines})
    assert len(runs) == 2
    for run in runs:
        mine = [(ln["env_index"], ln["episode_index"]) for ln in lines if ln["run_id"] == run]
        assert sorted(mine) == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert all(ln["min_clearance"] is None for ln in lines)  # no obstacle: null


# == issue 26: no bad number goes unnoticed ===========================================================
def _tiny_policy(**overrides):
    """A tiny untrained grid (51 values) formation_diffusion policy in eval mode."""
    import torch

    from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig
    from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy

    torch.manual_seed(0)
    kwargs = {
        **tiny_diffusion_kwargs(51),
        **standard_policy_kwargs(51),
        "noise_scheduler_type": "DDIM",
        "num_inference_steps": 4,
        **overrides,
    }
    return FormationDiffusionPolicy(FormationDiffusionConfig(**kwargs)).eval()


def _observation(seed: int = 0, dtype=None):
    import torch

    g = torch.Generator().manual_seed(seed)
    obs = {
        "observation.state": torch.randn(1, 7, generator=g),
        "observation.environment_state": torch.rand(1, 51, generator=g),
    }
    return {k: v.to(dtype) for k, v in obs.items()} if dtype is not None else obs


# -- item 4: one bad observation never poisons the episode ---------------------------------------------
@pytest.mark.parametrize("warm_start_step", [0, 1])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_observation_is_refused(warm_start_step, bad):
    policy = _tiny_policy(warm_start_step=warm_start_step)
    policy.reset()
    policy.select_action(_observation(0))
    obs = _observation(1)
    obs["observation.environment_state"][0, 12] = bad
    with pytest.raises(
        ValueError,
        match=rf"observation 'observation.environment_state' holds a non-finite value \({bad} at index \[0, 12\]\)",
    ):
        policy.select_action(obs)
    for seed in range(2, 12):  # the episode goes on with finite actions
        import torch

        assert torch.isfinite(policy.select_action(_observation(seed))).all()


@pytest.mark.parametrize(("dtype", "name"), [("int64", "torch.int64"), ("float64", "torch.float64")])
def test_wrongly_typed_observation_is_refused(dtype, name):
    import torch

    policy = _tiny_policy()
    policy.reset()
    with pytest.raises(
        TypeError,
        match=rf"observation 'observation.state' has dtype {name}, but the policy computes in torch.float32",
    ):
        policy.select_action(_observation(0, getattr(torch, dtype)))


def test_non_finite_chunk_never_enters_the_warm_start():
    import torch

    policy = _tiny_policy(warm_start_step=1)
    policy.reset()
    nan_noise = torch.full((1, 16, 2), float("nan"))
    with pytest.raises(FloatingPointError, match="non-finite action chunk"):
        policy.select_action(_observation(0), noise=nan_noise)
    actions = torch.stack([policy.select_action(_observation(seed)) for seed in range(1, 25)])  # 3 replans
    assert torch.isfinite(actions).all()


# -- item 5: a finished evaluation is never lost ------------------------------------------------------
def test_perfect_controller_on_100_scenes_draws_and_writes(tmp_path):
    from lerobot_formation.core.episodes.metrics import wilson_interval

    assert wilson_interval(100, 100) == (pytest.approx(0.963, abs=1e-3), 1.0)
    assert wilson_interval(500, 500)[1] == 1.0 and wilson_interval(0, 500)[0] == 0.0
    f = write_scenes(tmp_path / "s.json", [EMPTY_NEAR_GOAL] * 100)
    out = tmp_path / "out"
    assert bench_main(["--controllers", "pac", "--scenes", str(f), "--out", str(out), "--no-progress"]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["pac"]["success_rate"] == 1.0 and res["pac"]["success_ci95"][1] == 1.0
    assert (out / "success_rates.png").stat().st_size > 1000
    assert res["meta"]["figure_errors"] == []


def test_failing_figure_is_one_line_and_keeps_the_results(tmp_path, capsys, monkeypatch):
    import lerobot_formation.bench.plots as plots

    def broken(*args, **kwargs):
        raise RuntimeError("no renderer")

    monkeypatch.setattr(plots, "plot_trajectories", broken)
    f = write_scenes(tmp_path / "s.json", [EMPTY_NEAR_GOAL] * 2)
    out = tmp_path / "out"
    assert bench_main(["--controllers", "pac", "--scenes", str(f), "--out", str(out), "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert (
        "warning: figure pac_s_*.png not drawn: RuntimeError: no renderer" in err and "Traceback" not in err
    )
    res = json.loads((out / "results.json").read_text())
    assert res["pac"]["n_episodes"] == 2 and not res["meta"]["incomplete"]
    assert res["meta"]["figure_errors"] == ["figure pac_s_*.png not drawn: RuntimeError: no renderer"]
    assert "| Success Rate (%) |" in (out / "tables.md").read_text()
    assert (out / "success_rates.png").is_file()  # the other figures are still drawn


def test_full_disk_leaves_no_partial_file(tmp_path, capsys, monkeypatch):
    import errno

    f = write_scenes(tmp_path / "s.json", [EMPTY_NEAR_GOAL] * 2)
    out = tmp_path / "out"
    out.mkdir()
    (out / "results.json").write_text('{"earlier": "run"}')

    def no_space(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", no_space)
    with pytest.raises(SystemExit) as e:
        argv = ["--controllers", "pac", "--scenes", str(f), "--out", str(out), "--no-progress"]
        bench_main([*argv, "--overwrite"])  # replace the earlier run: never half of it
    assert e.value.code == 1
    line = last_error_line(capsys.readouterr().err)
    assert line == f"error: cannot write the results into {out}: [Errno 28] No space left on device"
    assert sorted(p.name for p in out.iterdir()) == ["results.json"]  # no temporary file, no figure
    assert (out / "results.json").read_text() == '{"earlier": "run"}'  # the earlier file is intact


# -- item 6: one lerobot-train run per output folder ---------------------------------------------------
_TRAIN_CONFIG = """
import sys
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.configs.default import DatasetConfig
from lerobot.configs.train import TrainPipelineConfig
import lerobot_formation.plugin
from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig

def train_config(data, out):
    policy = FormationDiffusionConfig(
        device="cpu", push_to_hub=False, horizon=16, n_action_steps=8, down_dims=(16, 32), kernel_size=3,
        n_groups=4, diffusion_step_embed_dim=16,
        input_features={"observation.state": PolicyFeature(type=FeatureType.STATE, shape=(7,))},
    )
    return TrainPipelineConfig(dataset=DatasetConfig(repo_id="local/x", root=data), policy=policy, output_dir=out)
"""


def _train_lock_script(tmp_path: Path, then: str) -> list[str]:
    data, out = tmp_path / "data", tmp_path / "run"
    data.mkdir(exist_ok=True)
    code = _TRAIN_CONFIG + f"\ntrain_config({str(data)!r}, {str(out)!r}).validate()\n" + then
    return [sys.executable, "-c", code]


def test_second_training_run_into_one_output_dir_refuses(tmp_path):
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    lock = tmp_path / ".run.train-lock"
    first = subprocess.Popen(
        _train_lock_script(tmp_path, "print('locked', flush=True); import time; time.sleep(120)"),
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert first.stdout.readline().strip() == "locked", first.stderr.read()
        # the second run's start-up in this process (validate() is where lerobot-train takes the lock;
        # the one-line form of a ConfigError on the command line: test_bad_config_value_...)
        from lerobot_formation.compat.run_checks import ConfigError

        config: dict = {}
        exec(_TRAIN_CONFIG, config)
        with pytest.raises(ConfigError) as e:
            config["train_config"](str(tmp_path / "data"), str(tmp_path / "run")).validate()
        assert str(e.value) == (
            f"--output_dir {tmp_path / 'run'} is in use by another lerobot-train run (pid {first.pid}); "
            f"wait for it to finish or choose another --output_dir (lock file {lock})"
        )
    finally:
        first.kill()  # SIGKILL: no cleanup runs, the lock file stays with a dead pid
        first.wait()
    assert lock.read_text().strip() == str(first.pid)
    third = subprocess.run(
        _train_lock_script(tmp_path, "print('ok')"), env=env, capture_output=True, text=True, timeout=300
    )
    assert third.returncode == 0, third.stderr[-2000:]  # a dead run's lock blocks nothing
    assert not lock.exists()  # released and removed at exit


# -- item 7: every config value checked at start-up, one line ------------------------------------------
@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        (
            "num_inference_steps",
            0,
            r"num_inference_steps must be null \(the training steps\) or in \[1, num_train_timesteps\] = \[1, 100\], got 0",
        ),
        ("num_inference_steps", -1, r"num_inference_steps must be null .* got -1"),
        ("num_inference_steps", 101, r"num_inference_steps must be null .* got 101"),
        ("safety_margin", float("nan"), r"config values must be finite numbers, got safety_margin=nan"),
        ("safety_mover_uncertainty", float("inf"), r"finite numbers, got safety_mover_uncertainty=inf"),
        ("ema_power", float("nan"), r"got ema_power=nan"),
        ("optimizer_lr", float("nan"), r"got optimizer_lr=nan"),
    ],
)
def test_config_values_are_checked(field, value, message):
    from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig

    with pytest.raises(ValueError, match=message):
        FormationDiffusionConfig(**{**tiny_diffusion_kwargs(51), field: value})


@pytest.mark.parametrize(
    ("cli", "args", "message"),
    [
        ("lerobot-eval", ["--policy.num_candidates=0"], "num_candidates must be >= 1, got 0"),
        (
            "lerobot-train",
            [
                "--policy.type=formation_diffusion",
                "--policy.push_to_hub=false",
                "--policy.num_inference_steps=0",
            ],
            "num_inference_steps must be null (the training steps) or in [1, num_train_timesteps] = [1, 100], got 0",
        ),
    ],
)
def test_bad_config_value_on_the_command_line_is_one_line(cli, args, message, tmp_path):
    if not CHECKPOINT.is_dir():
        pytest.skip("no pretrained checkpoint")
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    cmd = [str(Path(sys.executable).parent / cli), *args, f"--output_dir={tmp_path / 'out'}"]
    if cli == "lerobot-eval":
        cmd += [f"--policy.path={CHECKPOINT}", "--env.type=formation"]
    else:
        cmd += ["--dataset.repo_id=local/x", f"--dataset.root={tmp_path}"]
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 1
    assert "Traceback" not in proc.stderr and "Couldn't instantiate" not in proc.stderr, proc.stderr[-3000:]
    assert [ln for ln in proc.stderr.splitlines() if message.split(" ")[0] in ln] == [f"error: {message}"]


# -- item 8: fine-tuning on a dataset of another encoding ----------------------------------------------
def test_fine_tuning_on_another_encoding_fails_at_start_up(tmp_path):
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy

    import lerobot_formation.plugin  # noqa: F401

    if not CHECKPOINT.is_dir():
        pytest.skip("no pretrained checkpoint")
    data = tmp_path / "grid"  # 51 values; the checkpoint takes grid+list (66)
    lerobot_writer.generate(data, "local/grid", 2, workers=0, progress=False)
    cfg = PreTrainedConfig.from_pretrained(CHECKPOINT)  # as lerobot-train --policy.path does
    cfg.pretrained_path = CHECKPOINT
    with pytest.raises(ValueError) as e:
        make_policy(cfg, ds_meta=LeRobotDatasetMetadata("local/grid", root=data))
    assert str(e.value) == (
        "the dataset gives 'observation.environment_state' shape (51,) ('grid'), but the policy takes (66,) "
        "('grid+list'): train on a dataset of the policy's encoding (lerobot-formation-generate "
        "--obstacle-encoding grid+list)"
    )


# -- item 9: scenes files: size, count, keys, repeated obstacles ---------------------------------------
def test_scenes_file_limits_and_top_level_keys(tmp_path, monkeypatch):
    from lerobot_formation.core.world import scene_files as scene_mod

    g = tmp_path / "typo.json"
    g.write_text(json.dumps({"scenes": [EMPTY_NEAR_GOAL], "sceens": [EMPTY_NEAR_GOAL]}))
    with pytest.raises(
        ValueError, match=rf"scenes file {g}: unknown top-level key 'sceens'; allowed keys: 'scenes'"
    ):
        load_scenes(g)
    f = write_scenes(tmp_path / "s.json", [EMPTY_NEAR_GOAL] * 11)
    monkeypatch.setattr(scene_mod, "MAX_SCENES_PER_FILE", 10)
    checked = []
    monkeypatch.setattr(scene_mod, "scenes_from_list", lambda *a, **k: checked.append(a))
    with pytest.raises(
        ValueError, match=rf"scenes file {f} holds 11 scenes, more than the 10 a scenes file may hold"
    ):
        load_scenes(f)
    assert checked == []  # refused before any scene is checked (how fast: benchmarks/bench_refusals.py)
    size = f.stat().st_size
    monkeypatch.setattr(scene_mod, "MAX_SCENES_FILE_BYTES", 100)
    with pytest.raises(
        ValueError, match=rf"scenes file {f} has {size:,} bytes, more than the 100 a scenes file may have"
    ):
        load_scenes(f)


def test_repeated_obstacles_are_warned_about(tmp_path, caplog):
    import logging

    scenes = [
        {"obstacles": [[3.0, 3.0, 0.5]] * 50, "goal": [5.0, 5.0]},
        {"obstacles": [[3.0, 3.0, 0.5]], "goal": [5.0, 5.0]},
    ]
    f = write_scenes(tmp_path / "s.json", scenes)
    with caplog.at_level(logging.WARNING, logger="lerobot_formation.core.world.scene_files"):
        assert len(load_scenes(f)) == 2
    assert [r.getMessage() for r in caplog.records] == [
        f"scenes file {f}: scene 0 lists obstacle 0 [3.0, 3.0, 0.5] 50 times (49 repeated obstacles in the file)"
    ]


# -- item 10: registration is explicit, the package root stays light -----------------------------------
def test_register_registers_everything_and_the_package_root_stays_light():
    code = (
        "import sys, lerobot_formation\n"
        "assert 'torch' not in sys.modules and 'lerobot' not in sys.modules, 'the package root imported torch'\n"
        "from lerobot_formation.core.world.sampling import sample_scenes\n"
        "assert 'torch' not in sys.modules\n"
        "import lerobot_formation.plugin\n"
        "from lerobot.configs.policies import PreTrainedConfig\n"
        "from lerobot.envs.configs import EnvConfig\n"
        "from lerobot.processor import ProcessorStepRegistry\n"
        "print(PreTrainedConfig.get_choice_class('formation_diffusion').__name__, "
        "EnvConfig.get_choice_class('formation').__name__, "
        "'formation_egocentric_obstacles' in ProcessorStepRegistry.list())\n"
    )
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["FormationDiffusionConfig", "FormationEnvConfig", "True"]


def test_export_refuses_a_destination_it_did_not_write(tmp_path, monkeypatch):
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "export_pretrained", ROOT / "scripts" / "export_pretrained.py"
    )
    export = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(export)
    ckpt = tmp_path / "ckpt"
    ckpt.mkdir()
    (ckpt / "model.safetensors").write_bytes(b"")
    dest = tmp_path / "mine"
    dest.mkdir()
    (dest / "notes.txt").write_text("keep me")
    monkeypatch.setattr(sys, "argv", ["export", str(ckpt), str(dest), "--dataset.root", str(tmp_path)])
    with pytest.raises(SystemExit, match="is not a model folder written by this script"):
        export.main()
    assert (dest / "notes.txt").read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt", "mine"]  # no temporary left
