"""Realistic conditions of an episode (issue 23): limited sensing, noise, delay, rate limits, moving
obstacles. Every field's default is "off"; ``Conditions()`` is today's exact, static, fully known world.

This file holds the dataclass agreed between the two halves of issue 23 (notes/interface23.md); the
engine that applies the conditions lives with the rollout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields


@dataclass(frozen=True)
class Conditions:
    """Realistic conditions of an episode; every field's default is 'off'."""

    sensing_range: float | None = (
        None  # [m] obstacle observed once some agent came within this range of its surface
    )
    obstacle_memory: bool = True  # keep obstacles once seen
    obstacle_noise: float = (
        0.0  # [m] std of Gaussian noise on each observed obstacle centre (and radius), per step
    )
    pose_noise: float = (
        0.0  # [m] std of noise on the team's observed midpoint position (heading: pose_noise rad)
    )
    action_noise: float = 0.0  # fraction of the command (multiplicative Gaussian std)
    action_delay: int = 0  # [control steps] commands take effect this many steps late
    max_linear_accel: float | None = None  # [m/s^2] rate limit on the midpoint's v
    max_angular_accel: float | None = None  # [rad/s^2] rate limit on omega
    moving_obstacles: int = (
        0  # how many of a scene's obstacles move at constant velocity, bouncing in the bounds
    )
    obstacle_speed: float = 0.0  # [m/s] their speed

    @property
    def enabled(self) -> bool:
        """Whether any field differs from its default."""
        return self != Conditions()

    def __post_init__(self) -> None:
        for name in ("sensing_range", "max_linear_accel", "max_angular_accel"):
            value = getattr(self, name)
            if value is not None and (_not_number(value) or not value > 0):
                raise ValueError(f"conditions.{name} must be a positive number or None, got {value!r}")
        for name in ("obstacle_noise", "pose_noise", "action_noise", "obstacle_speed"):
            value = getattr(self, name)
            if _not_number(value) or value < 0:
                raise ValueError(f"conditions.{name} must be a number >= 0, got {value!r}")
        for name in ("action_delay", "moving_obstacles"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ValueError(f"conditions.{name} must be an integer >= 0, got {value!r}")
        if not isinstance(self.obstacle_memory, bool):
            raise ValueError(
                f"conditions.obstacle_memory must be true or false, got {self.obstacle_memory!r}"
            )


def _not_number(value) -> bool:
    return isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value)


CONDITION_FIELDS = tuple(f.name for f in fields(Conditions))
