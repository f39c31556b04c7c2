"""The safety layer's baselines run without a checkpoint (``bench.layer_controller``): "route-pursuit-safe"
acts bit for bit as the shipped checkpoint's replanner with nothing sampled (its layer around route
pursuit, told the level's conditions), the network never loaded; options of the layer apply."""

from pathlib import Path

import numpy as np

from lerobot_formation.bench.controllers import make_controller, safety_settings
from lerobot_formation.bench.settings import ControllerOptions
from lerobot_formation.core.episodes.levels import get_level
from lerobot_formation.core.episodes.rollout import rollout
from lerobot_formation.core.world.dynamics import FormationParams

SHIPPED = Path(__file__).resolve().parents[2] / "pretrained" / "formation_diffusion_route_v1"
STEPS = 60


def test_route_pursuit_safe_without_a_checkpoint_acts_as_the_checkpoints_layer():
    from lerobot_formation.bench.diffusion_controller import DiffusionController
    from lerobot_formation.bench.scene_sets import level_scenes
    from lerobot_formation.policy.replanner import ReplanExperiment

    level = get_level("level5")
    scenes = level_scenes("level5", 2)
    params = FormationParams()
    free = make_controller("route-pursuit-safe", params, ControllerOptions(conditions=level.conditions))
    assert not hasattr(free, "policy")
    with_checkpoint = DiffusionController(
        SHIPPED,
        params=params,
        overrides={"num_candidates": 10, "safety_filter": "cbf", **safety_settings(level.conditions)},
        experiment=ReplanExperiment(sampled=False),
    )
    runs = [
        rollout(scenes, ctrl, params, max_steps=STEPS, conditions=level.conditions)
        for ctrl in (free, with_checkpoint)
    ]
    np.testing.assert_array_equal(runs[0].actions, runs[1].actions)
    np.testing.assert_array_equal(runs[0].steps, runs[1].steps)
    assert free.stats == with_checkpoint.stats and free.stats["replans"] > 0
    # the shipped default's settings, told the level's world
    settings = free.replanner.layer.settings
    assert (settings.filter, settings.world.action_delay, settings.world.moving_obstacles) == ("cbf", 1, True)
    assert free.replanner.settings.num_candidates == 10


def test_the_layers_overrides_reach_the_checkpoint_free_controller():
    options = ControllerOptions(
        candidates=4, overrides={"safety_margin": 0.1, "n_action_steps": 2, "inference_backend": "eager"}
    )
    ctrl = make_controller("route-pursuit-safe", FormationParams(), options)
    assert ctrl.replanner.layer.settings.margin == 0.1 and ctrl.replanner.settings.n_action_steps == 2
    assert ctrl.replanner.settings.num_candidates == 4
    guided = make_controller("route-pursuit-guided", FormationParams(), ControllerOptions())
    assert guided.replanner.settings.num_candidates == 1 and not guided.replanner.best_of
    assert guided.replanner.layer.settings.filter == "none" and guided.replanner.settings.guidance > 0
