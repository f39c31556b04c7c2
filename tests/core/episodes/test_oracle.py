"""The oracle (``core.episodes.oracle``): branched teams step as their originals, its known future is the
world's, and a plan it finds replays to the outcome it found."""

import numpy as np
import pytest

from lerobot_formation.core.episodes.levels import get_level
from lerobot_formation.core.episodes.oracle import (
    CAUSES,
    SOLVED,
    OracleConfig,
    OracleController,
    _KnownFuture,
)
from lerobot_formation.core.episodes.rollout import SUCCESS, Teams, rollout
from lerobot_formation.core.world.sampling import sample_distribution

LEVEL5 = get_level("level5").conditions


def _scenes(n, first=5_000_000):
    return sample_distribution(np.arange(first, first + n), "structures")


def _same(a: Teams, b: Teams, rows_a, rows_b):
    for x, y in zip(a.state.arrays(), b.state.arrays(), strict=True):
        np.testing.assert_array_equal(x[rows_a], y[rows_b])
    np.testing.assert_array_equal(a.scenes.obstacles[rows_a], b.scenes.obstacles[rows_b])


def test_gathered_teams_step_as_their_originals():
    """Copies (repeats too) under level5's conditions step bit for bit as the teams they were taken
    from, each on its own noise stream; stepping a copy leaves the original where it was."""
    rng = np.random.default_rng(0)
    teams = Teams(_scenes(3), conditions=LEVEL5)
    for _ in range(7):
        teams.step(rng.uniform([0, -1], [0.5, 1], (3, 2)))
    before = teams.state.pose.copy()
    copies = Teams.gather([(teams, np.array([2, 0])), (teams, np.array([0, 1]))])  # rows 2, 0, 0, 1
    reference = teams.take(np.arange(3))
    for _ in range(25):
        command = rng.uniform([0, -1], [0.6, 1], (3, 2))
        reference.step(command)
        copies.step(command[[2, 0, 0, 1]])
        _same(reference, copies, [2, 0, 0, 1], [0, 1, 2, 3])
    np.testing.assert_array_equal(teams.state.pose, before)


def test_known_future_is_the_worlds():
    """The oracle's world (movers and noise looked up from one recording) steps a team as the level's
    world does, with the same commands."""
    rng = np.random.default_rng(1)
    world = Teams(_scenes(4), conditions=LEVEL5)
    known = world.take(np.arange(4))
    known.world = _KnownFuture.record(known.world, known.scenes.obstacles, 80)
    assert np.any(known.world.velocity)  # two movers a scene
    for _ in range(60):
        command = rng.uniform([0, -1.5], [0.6, 1.5], (4, 2))
        a, b = world.step(command), known.step(command)
        np.testing.assert_array_equal(a.outcome, b.outcome)
        _same(world, known, slice(None), slice(None))


@pytest.mark.parametrize("conditions", [None, LEVEL5], ids=["level3", "level5"])
def test_oracle_plans_replay_to_what_it_found(conditions):
    """``rollout`` replays each plan to the outcome the search found: solved scenes succeed, the others
    do not and carry a cause."""
    controller = OracleController(OracleConfig(passes=((0.65, 80, 0.0),)))
    rec = rollout(_scenes(2), controller, conditions=conditions)
    plans = controller.plans
    np.testing.assert_array_equal(rec.outcome == SUCCESS, plans.solved)
    assert plans.solved.any()
    assert set(plans.cause[plans.solved]) <= {SOLVED}
    assert set(plans.cause[~plans.solved]) <= set(CAUSES)
    assert (plans.steps[plans.solved] >= rec.steps[plans.solved]).all()


def test_oracle_needs_the_episodes_and_valid_settings():
    teams = Teams(_scenes(1))
    with pytest.raises(RuntimeError, match="plans offline"):
        OracleController().reset(teams.perceive())
    with pytest.raises(ValueError, match="expand must be >= 1, got 0"):
        OracleConfig(expand=0)
    with pytest.raises(ValueError, match=r"speeds must be fractions in \(0, 1\], got \(1.5,\)"):
        OracleConfig(speeds=(1.5,))
