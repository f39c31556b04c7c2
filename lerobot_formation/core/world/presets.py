"""Scene distributions: ``SceneConfig`` (SPEC defaults: the paper's layout) and the named presets,
mixtures and distribution specs drawn by ``core.world.sampling`` (``--scene-preset`` of the generator,
``<preset>:N`` scene sets of the bench).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lerobot_formation.core.world.scenes import MAX_GOAL_DISTANCE, PAPER_START

STRUCTURES = ("none", "bend", "trap")
# Obstacle slots of a structure: the bend's 4 walls of BEND_WALL circles (the corner drops a few),
# the trap's back wall of TRAP_BACK circles and its 2 arms of TRAP_ARM circles.
BEND_WALL, TRAP_BACK, TRAP_ARM = 9, 7, 4
STRUCTURE_SLOTS = {"none": 0, "bend": 4 * BEND_WALL, "trap": TRAP_BACK + 2 * TRAP_ARM}
WALL_RADIUS = (0.3, 0.4)  # [m] radius of the circles a structure's walls are built of


@dataclass(frozen=True)
class SceneConfig:
    """Distribution of random scenes (SPEC defaults)."""

    n_obstacles: tuple[int, int] = (3, 5)  # inclusive range of the obstacle count
    radius: tuple[float, float] = (0.3, 0.8)  # [m]
    centre_low: float = 1.5  # [m] obstacle centres uniform in [low, high]^2
    centre_high: float = 6.0  # [m]
    goal: tuple[float, float] = (5.0, 5.0)  # [m] midpoint goal
    start: tuple[float, float, float] = PAPER_START
    agent_radius: float = 0.1  # [m]
    half_width: float = 0.5  # [m] half the leader bar: inflation of the passage check (+ agent radius)
    # [m] farthest agent from the midpoint: goal margin. FormationGraph().radius() is sqrt(1.25) =
    # 1.11803...; kept at the rounded 1.118 because the exact value changes the validity of some
    # candidates (8 of the 633,600 paper-layout
    # candidates drawn for seeds 0-2999 and 1,000,000-1,000,299), so it would change scenes.
    formation_radius: float = 1.118
    start_margin: float = 0.2  # [m] clearance each start agent must keep
    grid_resolution: float = 0.1  # [m] passage check
    chunk: int = 64  # candidates drawn per rng call
    # Wider layouts (None / 0 everywhere: the paper's layout above, drawn exactly as before).
    goal_distance: tuple[float, float] | None = None  # [m] goal at this distance from the start ...
    goal_bearing: tuple[float, float] = (0.0, 2 * np.pi)  # [rad] ... in a world direction from this range
    heading_offset: tuple[float, float] = (0.0, 0.0)  # [rad] start heading = goal bearing + offset
    lateral: float = 2.5  # [m] obstacle centres within this distance of the start-goal line
    gate_prob: float = 0.0  # chance of a wall of 4 obstacles across the line with one narrow gap
    gate_gap: tuple[float, float] = (1.3, 1.7)  # [m] surface gap of the gate (the square needs 1.2)
    blocker_prob: float = 0.0  # chance of an obstacle centred on the straight line
    blocker_radius: tuple[float, float] = (0.5, 1.0)  # [m]
    paper_prob: float = 0.0  # chance that a candidate uses the paper's layout instead
    # A structure built of obstacles (``STRUCTURES``): "bend" a narrow corridor with one bend, the
    # team inside its first leg and the goal past its second; "trap" a U of obstacles between start
    # and goal opening toward the team. ``n_obstacles`` more are scattered along the start-goal line.
    structure: str = "none"

    def __post_init__(self) -> None:
        if self.structure not in STRUCTURES:
            raise ValueError(f"structure must be one of {STRUCTURES}, got {self.structure!r}")
        if self.structure != "none" and self.goal_distance is not None:
            raise ValueError(f"structure {self.structure!r} places its own goal; goal_distance must be None")
        lo, hi = self.n_obstacles
        if not 0 <= lo <= hi:
            raise ValueError(f"n_obstacles must be a range 0 <= lo <= hi, got {self.n_obstacles}")
        for name in ("gate_prob", "blocker_prob", "paper_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be a probability in [0, 1], got {getattr(self, name)}")
        if self.goal_distance is not None and not 0 < self.goal_distance[0] <= self.goal_distance[1]:
            raise ValueError(f"goal_distance must satisfy 0 < lo <= hi, got {self.goal_distance}")
        far = max(
            self.goal_distance[1] if self.goal_distance else 0.0,
            float(np.hypot(self.goal[0] - self.start[0], self.goal[1] - self.start[1])),
        )
        if far > MAX_GOAL_DISTANCE:
            raise ValueError(
                f"goals at most {MAX_GOAL_DISTANCE:g} m from the start are supported, got {far:g} m"
            )
        if not 0 < self.radius[0] <= self.radius[1]:
            raise ValueError(f"radius range must satisfy 0 < lo <= hi, got {self.radius}")
        if not self.centre_low < self.centre_high:
            raise ValueError(
                f"centre range must satisfy low < high, got {self.centre_low}, {self.centre_high}"
            )

    @property
    def wide(self) -> bool:
        """False for the paper's layout (fixed goal and start, centres in a square)."""
        return (
            self.goal_distance is not None
            or self.gate_prob > 0
            or self.blocker_prob > 0
            or self.structure != "none"
        )

    @property
    def max_obstacles(self) -> int:
        """Obstacle slots a scene of this distribution can need."""
        return (
            self.n_obstacles[1]
            + (4 if self.gate_prob > 0 else 0)
            + (1 if self.blocker_prob > 0 else 0)
            + STRUCTURE_SLOTS[self.structure]
        )


# Named scene distributions (``--scene-preset`` of the generator, ``<preset>:N`` scene sets of the bench).
# "paper" is SPEC's; the others are what a user meets beyond it: other goals and start headings,
# 0-10 obstacles of radius 0.2-1.0 along the way, narrow gates, obstacles straddling the straight line.
_OTHER_GOALS = dict(goal_distance=(5.0, 9.0), heading_offset=(-np.pi / 2, np.pi / 2))
SCENE_PRESETS: dict[str, SceneConfig] = {
    "paper": SceneConfig(),
    "goals": SceneConfig(**_OTHER_GOALS),
    "dense": SceneConfig(n_obstacles=(8, 10), radius=(0.2, 1.0), **_OTHER_GOALS),
    "gates": SceneConfig(n_obstacles=(0, 3), radius=(0.2, 1.0), gate_prob=1.0, **_OTHER_GOALS),
    "blockers": SceneConfig(n_obstacles=(0, 4), radius=(0.2, 1.0), blocker_prob=1.0, **_OTHER_GOALS),
    "wide": SceneConfig(
        n_obstacles=(0, 10),
        radius=(0.2, 1.0),
        gate_prob=0.25,
        blocker_prob=0.35,
        paper_prob=0.4,
        **_OTHER_GOALS,
    ),
}
HARD_PRESETS = ("gates", "blockers", "dense", "goals")
# Structures no preset above draws (issue 23): a narrow bent corridor, a concave trap, a crowd of more
# obstacles than the policy's encoding observes (12), long routes, goals behind the start.
SCENE_PRESETS.update(
    {
        "bend": SceneConfig(
            n_obstacles=(0, 0), structure="bend", heading_offset=(-0.2, 0.2), gate_gap=(1.8, 2.2)
        ),
        "trap": SceneConfig(n_obstacles=(0, 3), radius=(0.2, 0.6), structure="trap"),
        "crowd": SceneConfig(
            n_obstacles=(20, 30),
            radius=(0.15, 0.3),
            goal_distance=(8.0, 11.0),
            heading_offset=(-np.pi / 4, np.pi / 4),
            lateral=3.0,
        ),
        "long": SceneConfig(
            n_obstacles=(6, 12),
            radius=(0.2, 1.0),
            goal_distance=(14.0, 20.0),
            heading_offset=(-np.pi / 2, np.pi / 2),
            gate_prob=0.3,
            blocker_prob=0.5,
        ),
        "behind": SceneConfig(
            n_obstacles=(2, 6),
            radius=(0.2, 1.0),
            goal_distance=(4.0, 8.0),
            heading_offset=(2 * np.pi / 3, 4 * np.pi / 3),
            blocker_prob=0.5,
        ),
    }
)
STRUCTURE_PRESETS = ("bend", "trap", "crowd", "long", "behind")
# Mixtures of presets, a pure function of the seed: seed s draws from presets[s % len(presets)]
# (``sample_mixed``). "structures": the five above; "mixed-hard": the hard presets (unlike the
# ``hard:N`` scene set, whose blocks of N/4 scenes per preset depend on N).
SCENE_MIXES: dict[str, tuple[str, ...]] = {"structures": STRUCTURE_PRESETS, "mixed-hard": HARD_PRESETS}


def scene_preset(name: str) -> SceneConfig:
    if name not in SCENE_PRESETS:
        raise ValueError(f"scene preset must be one of {tuple(SCENE_PRESETS)}, got {name!r}")
    return SCENE_PRESETS[name]


def mix_max_obstacles(presets: tuple[str, ...]) -> int:
    """Obstacle slots of a mixture's scenes: its largest preset's (``sample_mixed`` pads to it)."""
    return max(scene_preset(name).max_obstacles for name in presets)


def distribution_entries(spec: str) -> tuple[str, ...]:
    """The entries of a scene distribution ``spec`` (the generator's ``--scene-preset``): a preset of
    ``SCENE_PRESETS``, a mixture of ``SCENE_MIXES``, or a comma-separated list of those; ValueError
    naming an unknown entry."""
    entries = tuple(e.strip() for e in str(spec).split(","))
    for e in entries:
        if e not in SCENE_PRESETS and e not in SCENE_MIXES:
            raise ValueError(
                f"scene preset {e!r} of {spec!r} is neither a preset {tuple(SCENE_PRESETS)} "
                f"nor a mixture {tuple(SCENE_MIXES)}"
            )
    return entries


def distribution_presets(spec: str) -> tuple[str, ...]:
    """Every preset a scene distribution ``spec`` can draw from (``distribution_entries``)."""
    names = [p for e in distribution_entries(spec) for p in SCENE_MIXES.get(e, (e,))]
    return tuple(dict.fromkeys(names))


def distribution_slots(spec: str) -> int:
    """Obstacle slots a scene of the distribution ``spec`` can need."""
    return max(scene_preset(p).max_obstacles for p in distribution_presets(spec))
