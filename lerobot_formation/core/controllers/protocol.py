"""The one interface every controller follows (``Controller``): PAC, MPPI and route pursuit here, the
bench's controllers (``bench.controllers``) too; ``core.episodes.rollout`` runs any of them.

A controller sees only what the robots perceive (``core.perception.conditions.Perception``: the observed
pose and velocity, the observed obstacles, their mask and velocities, the goal, and a map version
that changes when the observed obstacle set does): ``reset(view)`` once with the B teams' first
perception, then ``act(view, idx) -> (len(idx), 2)`` for the live episodes ``idx`` (global indices
into the batch), ``view`` holding their rows in that order. A controller that derives something from
the map (a cost-to-go) rebuilds it for a row when that row's ``map_version`` changes
(``map_obstacles``). A reference that plans offline on the true episodes (the oracle,
``core.episodes.oracle``) also has ``plan_episodes(scenes, conditions, max_steps)``, which
``core.episodes.rollout`` calls before ``reset``; no controller under test has it.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from lerobot_formation.core.perception.conditions import Perception


class Controller(Protocol):
    """A controller under test: it sees only the teams' ``Perception`` (module docstring)."""

    name: str

    def reset(self, view: Perception) -> None: ...

    def act(self, view: Perception, idx: np.ndarray) -> np.ndarray: ...


def map_obstacles(view: Perception) -> np.ndarray:
    """The observed obstacles (B, M, 3) a controller builds its map (cost-to-go) from:
    ``Perception.map_obstacles``, the static observed obstacles as observed when the map last changed
    (moving ones are padding: far away, radius 0, avoided locally); the true obstacles without
    conditions."""
    return view.map_obstacles
