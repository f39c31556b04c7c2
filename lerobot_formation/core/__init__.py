"""NumPy-only core of lerobot_formation: scenes, dynamics, formation control, PAC, metrics.

Nothing in this package imports torch, lerobot or gymnasium. Every function works on a batch of
scenes at once. Symbols used in shape comments:

    B  scenes (episodes) in the batch
    M  obstacles per scene (padded; padded rows sit far away with radius 0)
    N  agents (leaders first, then followers); L leaders (2), F followers
    E  formation edges
    K  candidate samples (MPPI, adaptive diffusion)
    T  time steps / horizon

Units: metres, seconds, radians.
"""

from lerobot_formation.core.encodings.obstacle_grid import environment_state, obstacle_grid
from lerobot_formation.core.world.dynamics import (
    FormationParams,
    FormationState,
    agent_positions,
    formation_error,
    initial_state,
    step,
)
from lerobot_formation.core.world.formation_graph import FormationGraph
from lerobot_formation.core.world.geometry import agent_clearances, midpoint_clearance
from lerobot_formation.core.world.presets import SceneConfig
from lerobot_formation.core.world.sampling import sample_scenes
from lerobot_formation.core.world.scene_files import load_scenes, save_scenes
from lerobot_formation.core.world.scenes import Scenes

__all__ = [
    "FormationGraph",
    "FormationParams",
    "FormationState",
    "SceneConfig",
    "Scenes",
    "agent_clearances",
    "agent_positions",
    "environment_state",
    "formation_error",
    "initial_state",
    "load_scenes",
    "midpoint_clearance",
    "obstacle_grid",
    "sample_scenes",
    "save_scenes",
    "step",
]
