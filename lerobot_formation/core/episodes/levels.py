"""The graded benchmark: named levels of increasing difficulty, each a fixed scene set and fixed conditions.

=======  =====================================================  =============================================
level    scenes (``scene_sets`` spec; seeds from 1,000,000)      conditions
=======  =====================================================  =============================================
level0   ``random``: the paper's layout                          none
level1   ``wide``: other goals and headings, gates, blockers      none
level2   ``mixed-hard``: gates, blockers, dense, other goals      none
level3   ``structures``: bends, traps, crowds, long, behind       none
level4   ``structures`` (the same scenes)                        sensing 4 m (memory), noise 0.02 m, action
                                                                 noise 5 %, 1-step delay, rate limits
level5   ``structures`` (the same scenes)                        sensing 3 m (memory), noise 0.05 m, action
                                                                 noise 5 %, 1-step delay, rate limits,
                                                                 2 obstacles moving at 0.3 m/s
=======  =====================================================  =============================================

Every level's scenes are a pure function of the seed (a mixture draws seed s from preset
``s % k``), so ``levelK:N`` is the first N scenes of level K whatever N, and levels 3-5 share their
scenes: the difference between them is the conditions alone. Evaluation seeds start at the level's
``seed`` (1,000,000, the project's unseen range); tune on seeds 5,000,000+ (``--seed 5000000``).

The bench runs a level as ``--scenes levelK:N``, ``lerobot-eval`` as ``--env.level=K --seed=1000000``
(the env config takes ``level_env_fields``; hence this module is in ``core``, below both).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from lerobot_formation.core.perception.conditions import Conditions
from lerobot_formation.core.world.sampling import UNSEEN_SEED_START

TUNING_SEED_START = 5_000_000  # seeds for choosing parameters; the levels' evaluation seeds start lower

# Rate limits of levels 4 and 5: 0 -> 0.5 m/s in 1 s, a full turn rate of 1.5 rad/s in 0.75 s.
_RATE_LIMITS = dict(max_linear_accel=0.5, max_angular_accel=2.0)


@dataclass(frozen=True)
class Level:
    """One level: ``scenes`` is a scene-set spec without its count (``scene_sets.parse_scenes``),
    ``seed`` the first seed, ``conditions`` what the engine applies."""

    name: str
    title: str
    scenes: str
    seed: int
    conditions: Conditions


LEVELS: dict[str, Level] = {
    level.name: level
    for level in (
        Level("level0", "the paper's layout", "random", UNSEEN_SEED_START, Conditions()),
        Level("level1", "wide scenes: other goals, gates, blockers", "wide", UNSEEN_SEED_START, Conditions()),
        Level(
            "level2",
            "hard presets: gates, blockers, dense, other goals",
            "mixed-hard",
            UNSEEN_SEED_START,
            Conditions(),
        ),
        Level(
            "level3",
            "structures: bent corridors, traps, crowds, long routes, goals behind",
            "structures",
            UNSEEN_SEED_START,
            Conditions(),
        ),
        Level(
            "level4",
            "structures, sensed within 4 m, noisy, 1 step late, rate limited",
            "structures",
            UNSEEN_SEED_START,
            Conditions(
                sensing_range=4.0,
                obstacle_noise=0.02,
                pose_noise=0.02,
                action_noise=0.05,
                action_delay=1,
                **_RATE_LIMITS,
            ),
        ),
        Level(
            "level5",
            "structures, sensed within 3 m, noisier, 1 step late, rate limited, 2 moving obstacles",
            "structures",
            UNSEEN_SEED_START,
            Conditions(
                sensing_range=3.0,
                obstacle_noise=0.05,
                pose_noise=0.05,
                action_noise=0.05,
                action_delay=1,
                moving_obstacles=2,
                obstacle_speed=0.3,
                **_RATE_LIMITS,
            ),
        ),
    )
}


def get_level(name: str) -> Level:
    """The level called ``name`` ("level0".."level5", or just its number); ValueError naming the choices."""
    key = f"level{name}" if str(name).isdigit() else str(name)
    if key not in LEVELS:
        raise ValueError(f"unknown level {name!r}; choose from {tuple(LEVELS)}")
    return LEVELS[key]


def level_env_fields(name: str) -> dict:
    """The env-config field values of level ``name``: ``scene_preset`` (a preset or a mixture of
    ``core.world.presets.SCENE_MIXES``; ``random`` is the "paper" preset) and every ``Conditions`` field.
    ``lerobot-eval`` takes the level's first seed as ``--seed``."""
    level = get_level(name)
    preset = "paper" if level.scenes == "random" else level.scenes
    return {"scene_preset": preset, **asdict(level.conditions)}
