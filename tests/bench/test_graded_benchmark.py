"""Issue 23: route pursuit, the structure presets, the graded levels and sharded evaluation."""

import dataclasses
import json

import numpy as np
import pytest

from lerobot_formation.bench.cli import main as bench_main
from lerobot_formation.bench.controllers import make_controller
from lerobot_formation.bench.evaluation import evaluate
from lerobot_formation.bench.merge import main as merge_main
from lerobot_formation.bench.scene_sets import level_scenes, parse_scenes, scene_set_conditions
from lerobot_formation.core.controllers.route_pursuit import RoutePursuitConfig, RoutePursuitController
from lerobot_formation.core.episodes.levels import LEVELS, get_level, level_env_fields
from lerobot_formation.core.episodes.rollout import SUCCESS, Teams, rollout
from lerobot_formation.core.perception.conditions import CONDITION_FIELDS, Conditions
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.core.world.presets import SCENE_MIXES, SCENE_PRESETS, STRUCTURE_PRESETS, scene_preset
from lerobot_formation.core.world.sampling import sample_mixed, sample_scenes
from lerobot_formation.core.world.scenes import FAR, Scenes
from lerobot_formation.core.world.validity import passage_exists, scene_validity
from lerobot_formation.envs.env_config import FormationEnvConfig, report_level_seed
from lerobot_formation.envs.vector_env import FormationVectorEnv


def _scene(obstacles, goal, start=(0.0, 0.0, np.pi / 2)) -> Scenes:
    obs = (
        np.array(obstacles, dtype=np.float64).reshape(1, -1, 3)
        if obstacles
        else np.array([[[FAR, FAR, 0.0]]])
    )
    return Scenes(obs, obs[..., 2] > 0, np.array([goal], np.float64), np.array([start], np.float64))


# -- route pursuit ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("obstacles", "goal"),
    [([], (3.0, 4.0)), ([(0.0, 3.0, 0.6)], (0.0, 6.0))],  # empty; one obstacle on the straight line
    ids=["empty", "blocked-line"],
)
def test_route_pursuit_reaches_the_goal(obstacles, goal):
    scenes = _scene(obstacles, goal)
    rec = rollout(scenes, RoutePursuitController())
    assert rec.outcome[0] == SUCCESS
    if obstacles:  # it went around, not through
        assert np.nanmin(rec.agent_clearance[0]) > 0


def test_route_pursuit_deterministic_and_in_bounds():
    params = FormationParams()
    scenes = sample_scenes(5_000_000 + np.arange(6), scene_preset("dense"))
    a = rollout(scenes, RoutePursuitController(params=params), params)
    b = rollout(scenes, RoutePursuitController(params=params), params)
    np.testing.assert_array_equal(a.poses, b.poses)
    # the raw commands, before the engine clips them
    ctrl = RoutePursuitController(params=params)
    view = Teams(scenes, params).perceive()
    ctrl.reset(view)
    rng = np.random.default_rng(0)
    for _ in range(5):  # random poses around the scenes, headings all round
        pose = np.c_[rng.uniform(-2, 8, (6, 2)), rng.uniform(-np.pi, np.pi, 6)]
        u = ctrl.act(dataclasses.replace(view, pose=pose), np.arange(6))
        assert u.shape == (6, 2) and np.isfinite(u).all()
        assert (u[:, 0] >= 0).all() and (u[:, 0] <= params.v_max).all()
        assert (np.abs(u[:, 1]) <= params.omega_max).all()


def test_route_pursuit_is_registered_and_its_config_checked():
    ctrl = make_controller("route-pursuit", FormationParams(), None)
    assert isinstance(ctrl, RoutePursuitController) and ctrl.name == "route-pursuit"
    with pytest.raises(ValueError, match="k must be a positive number, got -1"):
        RoutePursuitConfig(k=-1.0)


# -- structures ---------------------------------------------------------------------------------


@pytest.mark.parametrize("preset", STRUCTURE_PRESETS)
def test_structure_presets_valid_and_deterministic(preset):
    config = scene_preset(preset)
    seeds = 5_000_000 + np.arange(8)
    a, b = sample_scenes(seeds, config), sample_scenes(seeds, config)
    np.testing.assert_array_equal(a.obstacles, b.obstacles)
    np.testing.assert_array_equal(a.goal, b.goal)
    assert scene_validity(a, config)[0].all() and passage_exists(a, config).all()
    count = a.mask.sum(axis=1)
    dist = np.linalg.norm(a.goal - a.start[:, :2], axis=1)
    to_goal = np.arctan2(*(a.goal - a.start[:, :2])[:, ::-1].T)
    facing = np.cos(to_goal - a.start[:, 2])
    if preset == "bend":  # four walls of touching circles, the corner's inner ones dropped
        assert (count >= 20).all()
        # the straight line to the goal leaves the corridor: it passes an obstacle
        assert _line_blocked(a).all()
    if preset == "trap":
        assert (count >= 15).all() and _line_blocked(a).all()
    if preset == "crowd":
        assert (count >= 20).all() and (count > 12).all()  # more than the nearest 12 the policy sees
    if preset == "long":
        assert (dist >= 14).all()
    if preset == "behind":
        assert (facing < -0.4).all()


def _line_blocked(s: Scenes) -> np.ndarray:
    """Whether the straight segment start-goal passes within an obstacle's radius (B,)."""
    p, g = s.start[:, None, :2], s.goal[:, None]
    d = g - p
    t = np.clip(np.sum((s.obstacles[..., :2] - p) * d, -1) / np.sum(d * d, -1), 0, 1)
    gap = np.linalg.norm(p + t[..., None] * d - s.obstacles[..., :2], axis=-1) - s.obstacles[..., 2]
    return ((gap < 0) & s.mask).any(axis=1)


def test_structures_mix_is_a_function_of_the_seed():
    seeds = 5_000_000 + np.arange(10)
    mixed = sample_mixed(seeds, STRUCTURE_PRESETS)
    np.testing.assert_array_equal(mixed.seeds, seeds)
    for k, seed in enumerate(seeds):
        alone = sample_scenes([seed], scene_preset(STRUCTURE_PRESETS[seed % 5]))
        m = alone.obstacles.shape[1]
        np.testing.assert_array_equal(mixed.obstacles[k, :m], alone.obstacles[0])
        assert not mixed.mask[k, m:].any()
    # a prefix of a larger set is the smaller set
    np.testing.assert_array_equal(
        parse_scenes("structures:4", 7).obstacles, parse_scenes("structures:10", 7)[:4].padded(36).obstacles
    )


# -- levels -------------------------------------------------------------------------------------


def test_levels_fixed_and_deterministic():
    assert list(LEVELS) == [f"level{k}" for k in range(6)]
    for level in LEVELS.values():
        assert level.seed >= 1_000_000 and level.seed < 5_000_000  # evaluation seeds, not tuning ones
    a, b = level_scenes("level3", 5), level_scenes("level3", 5)
    np.testing.assert_array_equal(a.obstacles, b.obstacles)
    np.testing.assert_array_equal(a.seeds, 1_000_000 + np.arange(5))
    np.testing.assert_array_equal(parse_scenes("level3:5", None).obstacles, a.obstacles)
    np.testing.assert_array_equal(level_scenes("level5", 5).obstacles, a.obstacles)  # same scenes as 3
    assert level_scenes("level3", 3, seed=5_000_000).seeds[0] == 5_000_000
    hardest = get_level("5").conditions
    assert hardest.sensing_range == 3.0 and hardest.obstacle_memory and hardest.action_delay == 1
    assert hardest.moving_obstacles == 2 and hardest.obstacle_speed == 0.3 and hardest.enabled
    assert not get_level("level0").conditions.enabled


def test_level_errors_and_env_fields():
    with pytest.raises(ValueError, match=r"unknown level 'level9'; choose from \('level0'"):
        get_level("level9")
    with pytest.raises(ValueError, match="unknown level"):
        parse_scenes("level9:5", None)
    fields = level_env_fields("level5")
    assert fields["scene_preset"] == "structures" and fields["sensing_range"] == 3.0
    assert set(fields) == {"scene_preset", *CONDITION_FIELDS}
    assert level_env_fields("level0")["scene_preset"] == "paper" and "paper" in SCENE_PRESETS


def _same_scenes(a: Scenes, b: Scenes) -> None:
    for name in ("obstacles", "mask", "goal", "start", "seeds"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


# -- levels in lerobot-eval (--env.level) and mixtures as --env.scene_preset -------------------


@pytest.mark.parametrize("level", ["3", "level5"])
def test_env_level_plays_the_benchs_level_scenes_under_its_conditions(level):
    """``lerobot-eval --env.level=K --seed=1000000``: episode i resets with seed 1,000,000 + i, which
    is scene i of the bench's ``levelK:N``; the env has the level's conditions."""
    import draccus

    cfg = draccus.parse(FormationEnvConfig, args=[f"--level={level}"])
    want = get_level(level)
    assert cfg.conditions() == want.conditions and cfg.effective_scene_preset == "structures"
    env = cfg.make_env_factory()()
    bench = level_scenes(level, 2)
    for i in range(2):  # two scenes: two presets of the mixture (seed % 5)
        env.reset(seed=want.seed + i)
        _same_scenes(env.unwrapped.scene, bench[i : i + 1])
    assert env.unwrapped.conditions == (want.conditions if want.conditions.enabled else None)
    env.close()


def test_env_without_a_level_is_unchanged_and_level0_is_the_paper_layout():
    plain = FormationEnvConfig().gym_kwargs
    assert FormationEnvConfig().level is None and set(plain) == {
        "render_mode",
        "scenes_file",
        "obstacle_encoding",
        "scene_config",
    }
    assert plain["scene_config"] == SCENE_PRESETS["paper"]
    assert FormationEnvConfig(level="0").gym_kwargs == plain
    assert FormationEnvConfig(level="1").gym_kwargs["scene_config"] == SCENE_PRESETS["wide"]


def test_env_level_refuses_other_scene_or_condition_values():
    with pytest.raises(
        ValueError, match=r"env.level=5 fixes the scenes \(structures\).*drop --env.sensing_range=2.0,"
    ):
        FormationEnvConfig(level="5", sensing_range=2.0)
    with pytest.raises(ValueError, match="drop --env.scene_preset=wide --env.action_delay=3"):
        FormationEnvConfig(level="4", scene_preset="wide", action_delay=3)
    with pytest.raises(ValueError, match="drop --env.scenes_file=s.json"):
        FormationEnvConfig(level="3", scenes_file="s.json")
    with pytest.raises(ValueError, match=r"env.level: unknown level '9'; choose from \('level0'"):
        FormationEnvConfig(level="9")
    # the level's own values are no clash
    same = FormationEnvConfig(level="5", sensing_range=3.0, scene_preset="structures")
    assert same.conditions() == get_level("5").conditions


def test_env_scene_preset_takes_the_levels_mixtures():
    env = FormationEnvConfig(scene_preset="mixed-hard").make_env_factory()()
    env.reset(seed=1_000_003)
    _same_scenes(env.unwrapped.scene, parse_scenes("mixed-hard:4", 1_000_000)[3:4])
    env.close()
    venv = FormationVectorEnv(2, scene_mix=SCENE_MIXES["structures"])
    venv.reset(seed=1_000_000)
    _same_scenes(venv.scenes, parse_scenes("structures:2", 1_000_000))
    with pytest.raises(ValueError, match="env.scene_preset must be one of .*'structures', 'mixed-hard'"):
        FormationEnvConfig(scene_preset="mixed")
    with pytest.raises(ValueError, match="scene_mix must be a non-empty sequence"):
        FormationVectorEnv(1, scene_mix="structures")


def test_lerobot_eval_of_a_level_warns_about_another_seed(caplog):
    cfg = FormationEnvConfig(level="2")
    assert report_level_seed(cfg, 1_000_000) is None and report_level_seed(FormationEnvConfig(), 1000) is None

    with caplog.at_level("WARNING", logger="lerobot_formation"):
        cfg.run_eval_seed = 1000  # what lerobot-eval's pipeline config hands over (compat.run_checks)
        cfg.get_env_processors()
    assert "--env.level=2 with --seed=1000: episode i plays the scene of seed 1000 + i" in caplog.text
    assert "pass --seed=1000000" in caplog.text


def test_each_scene_set_runs_under_its_own_conditions():
    level5 = get_level("5").conditions
    assert scene_set_conditions("level5:3", Conditions()) == level5
    assert scene_set_conditions("random:3", Conditions(action_delay=2)) == Conditions(action_delay=2)
    with pytest.raises(
        ValueError, match=r"level5:3 fixes its own conditions .* drop --env flags \{'action_delay': 2\}"
    ):
        scene_set_conditions("level5:3", Conditions(action_delay=2))


def test_bench_unseen_level_runs_under_its_levels_conditions(tmp_path, monkeypatch, capsys):
    """``--unseen level4:N`` runs under level 4's conditions, the --scenes set under its own."""
    from types import SimpleNamespace

    import lerobot_formation.bench.cli as cli
    import lerobot_formation.policy.checkpoint as checkpoint

    ran = {}
    monkeypatch.setattr(cli, "run_set", lambda *a: ran.__setitem__(a[4], a[8]))  # label -> conditions
    monkeypatch.setattr(cli, "needs_policy", lambda name: True)  # the unseen set runs policy controllers
    policy = SimpleNamespace(config=SimpleNamespace(num_train_timesteps=100))
    monkeypatch.setattr(checkpoint, "load_policy", lambda path, device="cpu": (policy, None))
    argv = ["--controllers", "pac", "--policy.path", "p", "--no-figures", "--out", str(tmp_path)]
    argv.append("--overwrite")  # each run replaces the last
    assert cli.main([*argv, "--scenes", "random:1", "--unseen", "level4:1"]) == 0
    assert ran == {"random": Conditions(), "unseen": get_level("4").conditions}
    meta = json.loads((tmp_path / "results.json").read_text())["meta"]
    assert meta["conditions"] == {} and meta["unseen_conditions"] == get_level("4").conditions.changed()
    ran.clear()
    assert cli.main([*argv, "--scenes", "level5:1", "--unseen", "random:1"]) == 0
    assert ran == {"level5": get_level("5").conditions, "unseen": Conditions()}
    with pytest.raises(SystemExit):
        cli.main([*argv, "--scenes", "random:1", "--unseen", "level4:1", "--env.action_delay", "2"])
    assert "level4:1 fixes its own conditions" in capsys.readouterr().err


def _ablation():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "scripts" / "ablation.py"
    spec = importlib.util.spec_from_file_location("_test_ablation", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_ablation_runs_a_level_under_its_conditions_and_other_sets_under_the_flags(capsys):
    ablation = _ablation()
    runs = ablation.scene_set_runs(["level5:2", "random:1"], 1_000_000, Conditions())
    _same_scenes(runs["level5:2"][0], level_scenes("level5", 2))
    assert runs["level5:2"][1] == get_level("5").conditions and runs["random:1"][1] == Conditions()
    flagged = ablation.scene_set_runs(["random:1"], 1_000_000, Conditions(action_delay=2))
    assert flagged["random:1"][1] == Conditions(action_delay=2)
    # the CLI: --env flags like the bench's, refused with a level before anything is loaded
    with pytest.raises(SystemExit) as exit_info:
        ablation.main(["--new", "none", "--sets", "level5:1", "--env.action_delay", "2"])
    assert exit_info.value.code == 2 and "level5:1 fixes its own conditions" in capsys.readouterr().err


def test_route_pursuit_runs_under_conditions():
    scenes = _scene([], (3.0, 4.0))
    rec = evaluate(RoutePursuitController(), scenes, conditions=Conditions(action_delay=1))
    assert len(rec) == 1 and rec.outcome[0] == SUCCESS


# -- sharded evaluation -------------------------------------------------------------------------


def _bench(out, *extra):
    argv = ["--controllers", "route-pursuit,pac", "--scenes", "level0:5", "--seed", "5000000"]
    assert bench_main([*argv, "--no-figures", "--no-progress", "--out", str(out), *extra]) == 0
    return json.loads((out / "results.json").read_text())


def _without_wall_time(payload: dict) -> dict:
    for entries in payload["by_scenes"].values():
        for entry in entries.values():
            entry.pop("wall_time_s")
    return payload["by_scenes"]


def _edited_copy(src, dst, edit) -> str:
    """A copy of shard folder ``src`` at ``dst`` with ``edit(payload)`` applied to its results.json."""
    payload = json.loads((src / "results.json").read_text())
    edit(payload)
    dst.mkdir()
    (dst / "results.json").write_text(json.dumps(payload))
    return str(dst)


def test_three_shards_merge_to_the_whole_run(tmp_path, capsys):
    whole = _bench(tmp_path / "whole")
    shards = [_bench(tmp_path / f"s{i}", "--shard", f"{i}/3") for i in range(3)]
    assert [len(s["pac"]["episodes"]) for s in shards] == [2, 2, 1]
    assert [e["scene_index"] for e in shards[1]["pac"]["episodes"]] == [1, 4]
    assert [e["seed"] for e in shards[1]["pac"]["episodes"]] == [5_000_001, 5_000_004]
    folders = [str(tmp_path / f"s{i}") for i in (2, 0, 1)]  # any order
    assert merge_main([*folders, "--out", str(tmp_path / "merged")]) == 0
    merged = json.loads((tmp_path / "merged" / "results.json").read_text())
    assert merged["meta"]["shard"] is None and merged["meta"]["scenes"] == "level0:5"
    assert _without_wall_time(merged) == _without_wall_time(whole)
    assert [e["scene_index"] for e in merged["pac"]["episodes"]] == list(range(5))
    assert (tmp_path / "merged" / "tables.md").read_text() == (tmp_path / "whole" / "tables.md").read_text()

    # refused, and nothing written: a missing shard, a shard twice, other settings, a whole run
    capsys.readouterr()
    s0, s1, s2 = (tmp_path / f"s{i}" for i in range(3))
    cases = [
        ([s0, s1], "shards ['2/3'] are missing"),
        ([s0, s1, s2, s0], "shard 0/3 given twice"),
        ([s0, s1, _edited_copy(s2, tmp_path / "e1", lambda p: p["meta"].update(seed=7))], "seed = 7"),
        (
            [s0, s1, _edited_copy(s2, tmp_path / "e2", lambda p: p["by_scenes"]["level0"].pop("pac"))],
            "different controllers",
        ),
        (
            [s0, s1, _edited_copy(s2, tmp_path / "e3", lambda p: p["meta"].update(conditions={"x": 1}))],
            "conditions",
        ),
        (
            [s0, _edited_copy(s1, tmp_path / "e4", lambda p: p["meta"].update(shard="2/3")), s2],
            "shard 2/3 given twice",
        ),
        ([s0, s1, tmp_path / "whole"], "is not a shard"),
        ([s0, s1, tmp_path / "nowhere"], "no results.json"),
    ]
    for folders, message in cases:
        assert merge_main([*map(str, folders), "--out", str(tmp_path / "m2")]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "m2").exists()


def test_a_level_with_movers_counts_the_collisions_a_mover_struck_and_shards_merge_them(tmp_path, capsys):
    """``struck_by_mover`` (core.episodes.metrics.mover_strikes): in results.json per episode and counted in
    the summary, and a merge of shards recounts it from the episodes."""
    # from the 15th scene of level5: route pursuit is struck by a mover in the first of these two (a
    # short episode) and reaches the goal in the second, so each shard holds one of them
    argv = ["--controllers", "route-pursuit", "--scenes", "level5:2", "--seed", "1000014"]
    argv += ["--no-figures", "--no-progress"]
    assert bench_main([*argv, "--out", str(tmp_path / "whole")]) == 0
    whole = json.loads((tmp_path / "whole" / "results.json").read_text())["route-pursuit"]
    flags = [e["struck_by_mover"] for e in whole["episodes"]]
    assert all(isinstance(f, bool) for f in flags)
    assert whole["struck_by_mover"] == sum(flags) >= 1  # route pursuit meets level5's movers
    assert all(e["outcome"] == "collision" for e in whole["episodes"] if e["struck_by_mover"])
    assert whole["collisions"] >= whole["struck_by_mover"]
    printed = f"(collisions {whole['collisions']} ({whole['struck_by_mover']} struck by a mover), timeouts"
    assert printed in capsys.readouterr().out
    for i in range(2):
        assert bench_main([*argv, "--shard", f"{i}/2", "--out", str(tmp_path / f"s{i}")]) == 0
    assert merge_main([str(tmp_path / "s0"), str(tmp_path / "s1"), "--out", str(tmp_path / "m")]) == 0
    merged = json.loads((tmp_path / "m" / "results.json").read_text())["route-pursuit"]
    assert [e["struck_by_mover"] for e in merged["episodes"]] == flags == [True, False]
    assert merged["struck_by_mover"] == whole["struck_by_mover"] == 1
    assert printed in capsys.readouterr().out  # the merge prints it too
    assert (
        bench_main(
            [
                "--controllers",
                "route-pursuit",
                "--scenes",
                "level0:1",
                "--no-figures",
                "--out",
                str(tmp_path / "l0"),
            ]
        )
        == 0
    )
    assert "(collisions 0, timeouts" in capsys.readouterr().out  # nothing struck: nothing said


@pytest.mark.parametrize("shard", ["3/3", "1", "a/b", "-1/2"])
def test_bad_shard(shard, tmp_path, capsys):
    with pytest.raises(SystemExit):
        bench_main(["--scenes", "random:3", f"--shard={shard}", "--out", str(tmp_path)])
    assert f"--shard must be I/N with 0 <= I < N (e.g. 0/4), got {shard!r}" in capsys.readouterr().err


def test_bench_hands_a_levels_conditions_to_the_engine(tmp_path, capsys):
    argv = ["--controllers", "route-pursuit", "--no-figures", "--no-progress", "--out", str(tmp_path)]
    argv.append("--overwrite")  # each run replaces the last
    assert bench_main([*argv, "--scenes", "level4:1"]) == 0
    meta = json.loads((tmp_path / "results.json").read_text())["meta"]
    assert meta["seed"] == get_level("level4").seed
    assert meta["conditions"] == get_level("level4").conditions.changed()
    assert bench_main([*argv, "--scenes", "level3:1"]) == 0
    meta = json.loads((tmp_path / "results.json").read_text())["meta"]
    assert meta["seed"] == get_level("level3").seed and meta["conditions"] == {}
    with pytest.raises(SystemExit):  # a level fixes its conditions
        bench_main([*argv, "--scenes", "level3:1", "--env.sensing_range", "2"])
    assert "level3:1 fixes its own conditions" in capsys.readouterr().err


def test_a_shard_without_scenes_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit):
        bench_main(["--scenes", "random:2", "--shard", "2/3", "--out", str(tmp_path)])
    assert "--shard 2/3: the scene set random:2 has no scene of this shard" in capsys.readouterr().err
