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

from datasets_scripts import generate_pac_dataset as gen_mod
from lerobot_formation.bench.cli import main as bench_main
from lerobot_formation.bench.scene_sets import parse_scenes
from lerobot_formation.core.navigation import cost_to_go
from lerobot_formation.core.scene import SceneConfig, load_scenes, sample_scenes, scenes_from_list
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


def last_error_line(err: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert "Traceback" not in err, err
    return lines[-1]


# -- lerobot-formation-generate: killed runs, concurrent runs ----------------------------------------
def _start_generation(root: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "datasets_scripts.generate_pac_dataset", "--episodes", "400"]
    cmd += [
        "--batch-size",
        "8",
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


def _alive(procs) -> list[int]:
    import psutil

    out = []
    for p in procs:
        try:
            if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                out.append(p.pid)
        except psutil.NoSuchProcess:
            pass
    return out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="signals and /proc as on Linux")
def test_killed_generation_leaves_no_worker_and_a_rerun_no_temporary_folder(tmp_path):
    root = tmp_path / "ds"
    # SIGTERM: the handler raises SystemExit, so the cleanup runs at once
    proc = _start_generation(root)
    workers = _wait_until_writing(proc, root)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(30) == 128 + signal.SIGTERM
    time.sleep(1.0)
    assert _alive(workers) == []
    assert list(tmp_path.iterdir()) == []  # no temporary folder, no destination
    assert "Traceback" not in proc.stderr.read()
    # SIGKILL: no cleanup can run; the workers die with the parent, the rerun removes the folder
    proc = _start_generation(root)
    workers = _wait_until_writing(proc, root)
    proc.kill()
    proc.wait(30)
    time.sleep(1.5)
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
def test_far_goal_is_refused_fast(x, tmp_path, capsys):
    t0 = time.perf_counter()
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
    assert time.perf_counter() - t0 < 5


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
def _tiny_diffusion_kwargs(env_dim: int = 66) -> dict:
    """Config fields of a tiny diffusion policy on the formation features (a grid+list dataset)."""
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

    return dict(
        device="cpu",
        push_to_hub=False,
        input_features={
            OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(7,)),
            OBS_ENV_STATE: PolicyFeature(type=FeatureType.ENV, shape=(env_dim,)),
        },
        output_features={ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(2,))},
        horizon=16,
        n_action_steps=8,
        down_dims=(16, 32),
        kernel_size=3,
        n_groups=4,
        diffusion_step_embed_dim=16,
    )


def _stock_diffusion_checkpoint(path: Path) -> Path:
    import torch
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    torch.manual_seed(0)
    DiffusionPolicy(DiffusionConfig(**_tiny_diffusion_kwargs())).save_pretrained(path)
    return path


def _broken_checkpoint(tmp_path: Path, kind: str) -> Path:
    if kind == "missing":
        return tmp_path / "no_such_checkpoint"
    if kind == "stock":
        return _stock_diffusion_checkpoint(tmp_path / "stock")
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
    return path


@pytest.mark.parametrize(
    ("kind", "message"),
    [
        ("missing", "error: --policy.path: policy checkpoint folder {p} does not exist"),
        ("truncated", "error: --policy.path: {p}/model.safetensors cannot be loaded (truncated?)"),
        ("broken_config", "error: --policy.path: {p}/config.json is not valid JSON"),
        ("bad_field", "error: --policy.path: {p}/config.json is not a valid formation_diffusion config"),
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
        "error: controller diffusion-safe: the safety layer (num_candidates=10, safety_filter='cbf') needs an egocentric"
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
def test_env_encoding_that_does_not_fit_the_policy_fails_at_start_up():
    """lerobot-train calls make_env_pre_post_processors(env_cfg, policy_cfg) before its first step."""
    from lerobot.envs.factory import make_env_pre_post_processors

    from lerobot_formation.envs.env_config import FormationEnvConfig
    from lerobot_formation.policy.configuration_formation_diffusion import FormationDiffusionConfig

    policy_cfg = FormationDiffusionConfig(**_tiny_diffusion_kwargs(66), obstacle_encoding="grid+list")
    make_env_pre_post_processors(FormationEnvConfig(obstacle_encoding="grid+list"), policy_cfg)
    with pytest.raises(ValueError) as e:
        make_env_pre_post_processors(FormationEnvConfig(obstacle_encoding="grid"), policy_cfg)
    assert str(e.value) == (
        "--env.obstacle_encoding=grid gives 'observation.environment_state' 51 values, but the policy takes 66 "
        "(its dataset or checkpoint uses 'grid+list'): pass --env.obstacle_encoding=grid+list"
    )


def test_missing_dataset_root_offline_is_a_clear_error(tmp_path, monkeypatch):
    from huggingface_hub import constants
    from lerobot.configs.default import DatasetConfig

    import lerobot_formation.envs.env_config  # noqa: F401  (installs the check, as the plugin import does)

    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    missing = tmp_path / "no_dataset"
    with pytest.raises(
        ValueError, match=f"--dataset.root {missing} does not exist, and HF_HUB_OFFLINE is set"
    ):
        DatasetConfig(repo_id="local/x", root=str(missing))
    assert not missing.exists()
    DatasetConfig(repo_id="local/x", root=str(tmp_path))  # an existing root is fine
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", False)
    DatasetConfig(repo_id="local/x", root=str(missing))  # online: LeRobot downloads there


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
