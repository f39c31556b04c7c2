"""Route pursuit: a learning-free baseline that steers the leaders' midpoint down the route hint.

At every control step it computes the ``route_features`` that the default policy observes (the same
values unless a moving obstacle is observed, see below; ``core/encodings/route_encoding.py``: a grid
cost-to-go over the goal and the ``slots`` nearest obstacles, obstacles inflated by PAC's
``path_inflate``) and pursues its near point, the carrot ``NEAR_CELLS`` cells (1 m) down the steepest
descent from the midpoint (pure pursuit of a moving look-ahead point).

With the carrot (or, within ``r_goal`` of the goal, the goal itself) at body-frame coordinates
(x_b, y_b) (x right, y along the heading) and d_goal the midpoint's distance to the goal::

    e     = atan2(-x_b, y_b)                                        heading error, + is to the left
    v     = v_max * max(cos e, 0)^2 * clip(d_goal / d0, v_min_frac, 1)
    omega = clip(k * e, -omega_max, omega_max)

The cos^2 factor stops the team while it turns toward a carrot behind it (the followers' rear corners
swing out when the square turns fast), and the last factor slows it down within d0 of the goal.
There is no footprint check and no memory: the cost-to-go's inflation alone keeps the square off
the obstacles. Deterministic: the same scene and pose give the same command.

It plans only with what the team perceives (``core.perception.conditions.Perception``) and the observed pose: the
route on its map (``map_obstacles``: the static observed obstacles as observed when the map last
changed, PAC's map and the policy's route hint), plus the observed moving obstacles where they are
now, since nothing else steers it around them (so under moving obstacles its field is rebuilt at every
step once one is observed, and its route differs from the policy's hint, which leaves them out).
Between map changes, with no moving obstacle observed, the cost-to-go is a cache hit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lerobot_formation.core.encodings.encoding import BODY_POSE, world_to_body
from lerobot_formation.core.encodings.route_encoding import route_features
from lerobot_formation.core.perception.conditions import Perception
from lerobot_formation.core.world.dynamics import FormationParams


@dataclass(frozen=True)
class RoutePursuitConfig:
    """Gains of route pursuit; defaults tuned on tuning seeds 5,000,000+ (docs/log.md, "Route pursuit: tuning its gains")."""

    v_max: float = 0.5  # [m/s] cruise speed (the dynamics clip at FormationParams.v_max = 0.6)
    k: float = 2.0  # [1/s] heading gain
    d0: float = 1.0  # [m] slow down within this distance to the goal ...
    v_min_frac: float = 0.3  # ... to no less than this fraction of v_max
    r_goal: float = 0.6  # [m] within this distance, aim at the goal instead of the carrot
    slots: int = 12  # obstacles observed (the nearest ``slots``, as the default policy's encoding)
    whole_map: bool = False  # the route planned on every map obstacle (``nearest+maproute``), not the slots

    def __post_init__(self) -> None:
        for name in ("v_max", "k", "d0", "r_goal"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"RoutePursuitConfig.{name} must be a positive number, got {value}")
        if not 0.0 <= self.v_min_frac <= 1.0:
            raise ValueError(f"RoutePursuitConfig.v_min_frac must be in [0, 1], got {self.v_min_frac}")
        if self.slots < 1:
            raise ValueError(f"RoutePursuitConfig.slots must be >= 1, got {self.slots}")


def heading_error(target_body: np.ndarray) -> np.ndarray:
    """Angle (B,) from the heading to body-frame points (B, 2) (x right, y ahead), + to the left."""
    return np.arctan2(-target_body[:, 0], target_body[:, 1])


def pursuit_command(
    target_body: np.ndarray, goal_distance: np.ndarray, config: RoutePursuitConfig, omega_max: float
) -> np.ndarray:
    """[v, omega] (B, 2) toward body-frame targets (B, 2) (see the module docstring)."""
    e = heading_error(target_body)
    slow = np.clip(goal_distance / config.d0, config.v_min_frac, 1.0)
    v = config.v_max * np.maximum(np.cos(e), 0.0) ** 2 * slow
    omega = np.clip(config.k * e, -omega_max, omega_max)
    return np.stack([v, omega], axis=-1)


def route_command(
    target_body: np.ndarray, pose: np.ndarray, goal: np.ndarray, config: RoutePursuitConfig, omega_max: float
) -> np.ndarray:
    """[v, omega] (B, 2) toward body-frame targets (B, 2) (the carrot), or within ``r_goal`` of the goal
    (B, 2) the goal itself, from midpoint poses (B, 3) (``pursuit_command``)."""
    target = np.array(target_body, dtype=np.float64)
    d_goal = np.hypot(goal[:, 0] - pose[:, 0], goal[:, 1] - pose[:, 1])
    near = d_goal < config.r_goal
    target[near] = world_to_body(goal, pose)[near]
    return pursuit_command(target, d_goal, config, omega_max)


class RoutePursuitController:
    """Route pursuit behind the ``protocol.Controller`` interface (``reset(view)``, ``act(view, idx)``)."""

    name = "route-pursuit"

    def __init__(self, config: RoutePursuitConfig | None = None, params: FormationParams | None = None):
        self.config = config or RoutePursuitConfig()
        self.params = params or FormationParams()

    def reset(self, view: Perception) -> None:
        """Nothing to build: the route is looked up on the perception's map at every step (cached fields)."""

    def act(self, view: Perception, idx: np.ndarray) -> np.ndarray:
        obstacles, mask, goal = view.obstacles, view.mask, view.goal
        pose = np.asarray(view.pose, dtype=np.float64)
        # no local avoidance: observed moving obstacles join the map where they are now
        moving = np.any(view.obstacle_velocity != 0, axis=-1)
        plan = np.where(moving[..., None], obstacles, view.map_obstacles)
        features = route_features(obstacles, mask, goal, pose, self.config.slots, plan, self.config.whole_map)
        # the 1 m carrot, body frame
        return route_command(features[:, :2], pose, goal, self.config, self.params.omega_max)


def make_route_pursuit(
    name: str, params: FormationParams, options=None, bundle=None
) -> RoutePursuitController:
    """The controller registry's factory (``controllers.CONTROLLER_FACTORIES``): default gains, and the
    route hint of the bench's checkpoint where one is loaded (``bundle``: its policy observes
    ``nearest+maproute``, so route pursuit plans on the whole map too), so that both see the same hint."""
    encoding = getattr(getattr(bundle[0], "config", None), "obstacle_encoding", None) if bundle else None
    return RoutePursuitController(RoutePursuitConfig(whole_map=encoding == "nearest+maproute"), params)


def pursuit_chunk(
    route_body: np.ndarray,
    goal_body: np.ndarray,
    steps: int,
    dt: float,
    omega_max: float,
    config: RoutePursuitConfig | None = None,
    start: np.ndarray | None = None,
) -> np.ndarray:
    """Route pursuit's command sequence (B, steps, 2) over one chunk, from what the route hint
    observes: ``route_body`` (B, 4) the near and far carrots, ``goal_body`` (B, 2) the goal, in the
    body frame of the midpoint now (x right, y ahead; the ``nearest+route`` encoding's values).

    The midpoint is rolled out as a unicycle (``dynamics.step_midpoint``) from ``start`` (B, 3), a
    pose in that frame (None: the midpoint now, ``core.encodings.encoding.BODY_POSE``; the safety layer's
    lookahead starts it at each candidate's end); at each step it pursues (``pursuit_command``) the
    near carrot until within half its starting distance of it, then the far one, and the goal within
    ``r_goal`` of it: pure pursuit of the polyline the hint gives, which the safety layer's best-of-K
    scores beside the sampled chunks (``core.safety.layer.ROUTE_PROPOSAL``).
    """
    config = config or RoutePursuitConfig()
    route_body = np.asarray(route_body, dtype=np.float64)
    goal_body = np.asarray(goal_body, dtype=np.float64)
    B = len(route_body)
    pose = np.tile(BODY_POSE, (B, 1)) if start is None else np.array(start, dtype=np.float64)
    # pursuit_command, world_to_body and step_midpoint written out on coordinate arrays, operation for
    # operation (the same numbers): a 2 s lookahead of 46 candidates runs 20 steps of these per replan
    x, y, phi = pose[:, 0], pose[:, 1], pose[:, 2]
    near_x, near_y, far_x, far_y = (route_body[:, i] for i in range(4))
    goal_x, goal_y = goal_body[:, 0], goal_body[:, 1]
    switch = 0.5 * np.sqrt((near_x - x) ** 2 + (near_y - y) ** 2)
    passed = np.zeros(B, dtype=bool)
    out = np.empty((B, steps, 2))
    # np.minimum/np.maximum for np.clip (the same numbers, half the call overhead on a few rows)
    v_max, gain, d0, v_min_frac, r_goal = config.v_max, config.k, config.d0, config.v_min_frac, config.r_goal
    for k in range(steps):
        passed |= np.sqrt((near_x - x) ** 2 + (near_y - y) ** 2) < switch
        d_goal = np.sqrt((goal_x - x) ** 2 + (goal_y - y) ** 2)
        at_goal = d_goal < r_goal
        aim_x, aim_y = near_x, near_y  # np.where only where some row needs it
        if passed.any():
            aim_x, aim_y = np.where(passed, far_x, near_x), np.where(passed, far_y, near_y)
        if at_goal.any():
            aim_x, aim_y = np.where(at_goal, goal_x, aim_x), np.where(at_goal, goal_y, aim_y)
        a = phi - np.pi / 2
        c, s = np.cos(a), np.sin(a)
        dx, dy = aim_x - x, aim_y - y
        e = np.arctan2(-(dx * c + dy * s), -dx * s + dy * c)  # heading_error of the body-frame aim
        slow = np.minimum(np.maximum(d_goal / d0, v_min_frac), 1.0)
        v = v_max * np.maximum(np.cos(e), 0.0) ** 2 * slow
        omega = np.minimum(np.maximum(gain * e, -omega_max), omega_max)
        out[:, k, 0], out[:, k, 1] = v, omega
        x, y, phi = x + v * np.cos(phi) * dt, y + v * np.sin(phi) * dt, phi + omega * dt
    return out
