"""bench.level_report: the report scripts' shared flags, overrides and run."""

from __future__ import annotations

import argparse
from dataclasses import replace

import pytest

from lerobot_formation.bench import level_report
from lerobot_formation.core.episodes.levels import get_level
from lerobot_formation.core.safety.layer import KnownWorld, known_world


def _parse(*flags: str) -> argparse.Namespace:
    ap = argparse.ArgumentParser()
    level_report.add_arguments(ap)
    return ap.parse_args(["--level", "level0", *flags])


def _overrides(args: argparse.Namespace) -> dict:
    return level_report.safety_overrides(**{k: getattr(args, k) for k in level_report.SAFETY_FLAGS})


def test_no_flag_keeps_the_checkpoints_settings():
    assert _overrides(_parse()) == {}


def test_each_flag_names_its_config_field():
    args = _parse(
        "--safety-margin", "0.11", "--layer-ignores-noise", "--layer-ignores-motion", "--horizon", "0",
        "--chunk-smoothing", "0", "--mover-uncertainty", "0",
    )  # fmt: skip
    assert _overrides(args) == {
        "safety_margin": 0.11,
        "safety_horizon": 0,
        "safety_world": KnownWorld(),  # told nothing: the world given (None) without noise and motion
        "chunk_smoothing": 0,
        "safety_mover_uncertainty": 0.0,
    }
    level5 = known_world(get_level("level5").conditions)
    assert level5.moving_obstacles and level5.action_delay and level5.obstacle_noise
    ignores = level_report.safety_overrides(layer_ignores_noise=True, world=level5)
    assert ignores == {"safety_world": replace(level5, obstacle_noise=0.0, pose_noise=0.0)}
    ignores = level_report.safety_overrides(layer_ignores_motion=True, world=level5)
    assert ignores == {"safety_world": replace(level5, moving_obstacles=False)}
    for retired in ("--route-proposal", "--route-lookahead", "--coherence", "--halt-lookahead"):
        with pytest.raises(SystemExit):
            _parse(retired, "0")


def test_bad_inputs_name_the_value():
    with pytest.raises(ValueError, match="level9"):
        level_report.run_level("pac", "level9", 1)
    with pytest.raises(ValueError, match="needs a policy path"):
        level_report.run_level("diffusion-safe", "level0", 1)
    with pytest.raises(ValueError, match="no replanner"):
        level_report.run_level("pac", "level0", 1, wrap_replanner=lambda replanner, steps: replanner)


def test_a_run_is_the_levels_scenes_under_its_conditions_and_its_summary_counts_them():
    run = level_report.run_level("pac", "level4", 2, seed=5_000_000, max_steps=30)
    assert run.level == "level4" and len(run.records.outcome) == 2
    assert run.scenes.seeds.tolist() == [5_000_000, 5_000_001]
    summary = run.summary("3 of something")
    assert summary.startswith("pac on level4 (2 scenes from seed 5000000): success 0.0 %, collisions 0")
    assert summary.endswith("timeouts 2; 3 of something; no successful episode")


def test_the_flags_pass_on_by_name_to_the_run():
    """Every destination of the shared flags is a keyword of ``run_flags``, which runs what
    ``run_level`` runs with the same settings."""
    args = _parse("--scenes", "2", "--max-steps", "30", "--safety-margin", "0.07")
    settings = {k: getattr(args, k) for k in level_report.RUN_FLAGS}
    assert set(settings) == set(level_report.RUN_FLAGS)
    run = level_report.run_flags("pac", **settings)
    same = level_report.run_level("pac", "level0", 2, max_steps=30, overrides={"safety_margin": 0.07})
    assert run.summary() == same.summary()
    assert run.seed == same.seed == 5_000_000


def test_the_recording_replanner_records_what_the_controller_did():
    """The bench's safety-layer controller with the recording replanner: every episode replans at its
    first step, the recorded replans, proposals and filter changes are the replanner's own counts,
    and every replan recorded how many of its scored chunks were safe (K samples and the proposal)."""
    from pathlib import Path

    import numpy as np

    from lerobot_formation.bench.controllers import make_controller
    from lerobot_formation.bench.scene_sets import level_scenes
    from lerobot_formation.bench.settings import ControllerOptions
    from lerobot_formation.core.episodes.rollout import rollout
    from lerobot_formation.core.world.dynamics import FormationParams

    root = Path(__file__).resolve().parents[2]
    params = FormationParams()
    options = ControllerOptions(
        policy_path=str(root / "pretrained" / "formation_diffusion_route_v1"), candidates=3
    )
    controller = make_controller("diffusion-safe", params, options)
    controller.replanner = level_report.recording_replanner(controller.replanner, 20)
    rollout(level_scenes("level0", 2, seed=5_000_000), controller, params, max_steps=20)
    recorder = controller.replanner
    events = recorder.events
    assert set(events) == set(level_report.EVENTS)
    assert events["replan"][:, 0].all()
    replanned = events["replan"] | events["replan_cut"]
    assert replanned.sum() == controller.stats["replans"] > 2
    assert events["proposal"].sum() == controller.stats["proposals"]
    assert events["search"].sum() == controller.stats["searched"]
    assert events["escape"].sum() == controller.stats["escapes"]
    assert events["filter"].sum() == controller.stats["filter_interventions"]
    scored = 3 + 1  # the samples and route pursuit's proposal (no movers: no search)
    assert np.all(recorder.scored[replanned] == scored) and np.all(recorder.scored[~replanned] == -1)
    assert np.all((recorder.safe_count[replanned] >= 0) & (recorder.safe_count[replanned] <= scored))
    # a fallback is a replan where nothing scored was safe
    assert np.all(recorder.safe_count[events["fallback"]] == 0)
