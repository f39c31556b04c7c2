"""PAC, the demonstrator, on 200 valid random scenes (slow tier) and on the first 20 (fast tier)."""

import numpy as np
import pytest

from lerobot_formation.core.controllers.pac import PACController
from lerobot_formation.core.episodes.rollout import COLLISION, SUCCESS, rollout
from lerobot_formation.core.world.sampling import sample_scenes


@pytest.mark.slow
def test_pac_success_on_200_random_scenes():
    """Measured 196/200 on seeds 0..199 (and the rate on 1000 scenes is in the README). The goal is
    95 %; the scenes are fixed by their seeds, so the run is deterministic and the threshold is the
    goal itself: a regression of PAC below it fails."""
    rec = rollout(sample_scenes(np.arange(200)), PACController())
    success = np.mean(rec.outcome == SUCCESS)
    assert success >= 0.95, f"PAC success {success:.1%}"
    assert np.sum(rec.outcome == COLLISION) <= 2


def test_pac_success_smoke_on_20_random_scenes():
    """The fast tier's copy of the test above on seeds 0..19, with the same thresholds."""
    rec = rollout(sample_scenes(np.arange(20)), PACController())
    success = np.mean(rec.outcome == SUCCESS)
    assert success >= 0.95, f"PAC success {success:.1%}"
    assert np.sum(rec.outcome == COLLISION) <= 2
