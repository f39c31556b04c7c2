"""Realistic conditions of an episode: limited sensing, noise, late and inexact commands, rate limits
and moving obstacles, batched over B teams (numpy only). Every field of ``Conditions`` defaults to off;
with all of them off ``core.episodes.rollout.Teams`` never builds a ``ConditionedWorld`` and every trajectory,
observation and dataset byte is what it was before the conditions existed.

What the robot perceives (``Perception``) is all a controller under test and every observation
encoding get:

- sensing: an obstacle is observed once some agent has come within ``sensing_range`` of its surface
  (agent centre to obstacle surface, checked at the episode's start and after every control step);
  with ``obstacle_memory`` it stays observed, and keeps being tracked, from then on; without, it is
  observed only while some agent is within range. Unobserved slots look like padding: (FAR, FAR, 0),
  mask False, velocity 0.
- noise: each control step every observed obstacle's centre and radius get Gaussian noise of std
  ``obstacle_noise`` [m] (radius kept >= ``MIN_OBSERVED_RADIUS``), the midpoint pose gets
  ``pose_noise`` on x, y [m] and on the heading [rad]. The observed velocities (the team's own and the
  obstacles') are exact.
- commands: the command sent at step t is executed at step t + ``action_delay`` (a FIFO per team;
  during the first ``action_delay`` steps the team executes zeros, i.e. holds still), multiplied
  component-wise by (1 + ``action_noise`` z), then rate limited (``dynamics.rate_limit``:
  ``max_linear_accel``, ``max_angular_accel``).
- moving obstacles: ``moving_obstacles`` of a scene's obstacles move at ``obstacle_speed`` in
  directions drawn from the scene's seed (or the scene's own ``velocities``), bouncing off the scene's
  bounds (``scene_bounds``), off the start and goal zones (the fairness rule below) and off every
  other obstacle, static or moving (a mover never overlaps another obstacle: it is a body a robot
  could meet, never one that comes out of a wall). Collisions with them count like any other and
  end the episode.

Fairness: a moving obstacle never enters the start zone (a disc of ``ZONE_RADIUS`` around the start
midpoint) nor the goal zone (the same around the goal): it bounces off their edge as off a wall. Only
obstacles that start outside both zones and clear of every other obstacle are chosen to move (a
circle of a wall stays in the wall), so a team is never hit where it starts and a goal is never
blocked for good; the static layout is the scene's own (valid: a passage exists).

Randomness: every team has its own ``np.random.Generator`` seeded with (scene seed, ``NOISE_TAG``)
(a scene without a seed, -1, uses its row in the batch), and draws one fixed-size vector per control
step (pose 3, action 2, then 3 per real obstacle of its scene): a team's draws do not depend on the
other teams of its batch, nor on which noises are on. Motion directions come from (scene seed,
``MOTION_TAG``).
"""

from __future__ import annotations

import copy
import math
import typing
from dataclasses import dataclass, field, fields

import numpy as np

from lerobot_formation.core.world.dynamics import (
    FormationParams,
    FormationState,
    agent_positions,
    clip_action,
    rate_limit,
)
from lerobot_formation.core.world.geometry import obstacle_gaps
from lerobot_formation.core.world.scenes import FAR, Scenes

NOISE_TAG = 0x6E6F6973  # "nois": the per-step noise stream of an episode
MOTION_TAG = 0x6D6F7665  # "move": which obstacles move, and where to
ZONE_RADIUS = 1.5  # [m] start and goal zones (formation radius 1.12 m + agent radius + margin)
BOUNDS_MARGIN = 1.0  # [m] the scene's bounds: its obstacles, start and goal, plus this margin
MIN_OBSERVED_RADIUS = 0.05  # [m] a noisy radius never drops below this (the slot stays an obstacle)


def condition(
    default,
    help: str,
    *,
    unit: str = "",
    gt: float | None = None,
    ge: float | None = None,
    le: float | None = None,
):
    """One field of ``Conditions``, declared once: its default (off), its help and unit (the env
    config's ``--env.<field>`` and the CLI flags show ``[unit] help``: ``condition_help``) and its
    bounds (``gt`` / ``ge``: the value must be > / >= this, ``le``: <= this; checked by
    ``Conditions.__post_init__``, whose error names the field and the value). The field's kind comes
    from its annotation: ``bool``, ``int``, ``float`` or ``float | None`` (None: off)."""
    return field(default=default, metadata={"help": help, "unit": unit, "gt": gt, "ge": ge, "le": le})


@dataclass(frozen=True)
class Conditions:
    """Realistic conditions of an episode; every field's default is 'off' (module docstring). Each
    field is declared here once, with its help, unit and bounds (``condition``); the env config's
    fields (``envs.env_config.ConditionFields``) and the CLI flags (``envs.condition_flags``) are
    built from these declarations."""

    sensing_range: float | None = condition(
        None,
        "an obstacle is observed once some agent came within this range of its surface "
        "(unset: every obstacle is observed from the start)",
        unit="m",
        gt=0,
    )
    obstacle_memory: bool = condition(
        True, "keep obstacles once seen (true/false; false: only while within range)"
    )
    obstacle_noise: float = condition(
        0.0,
        "std of the per-step Gaussian noise on each observed obstacle's centre and radius",
        unit="m",
        ge=0,
    )
    pose_noise: float = condition(
        0.0,
        "std of the per-step noise on the observed midpoint position (heading: the same in rad)",
        unit="m",
        ge=0,
    )
    action_noise: float = condition(
        0.0, "std of the multiplicative noise on each executed command component (a fraction)", ge=0
    )
    action_delay: int = condition(
        0,
        "commands take effect this many steps late (the team holds still until then)",
        unit="control steps",
        ge=0,
        le=1000,
    )
    max_linear_accel: float | None = condition(
        None, "rate limit on the executed v (unset: none)", unit="m/s^2", gt=0
    )
    max_angular_accel: float | None = condition(
        None, "rate limit on the executed omega (unset: none)", unit="rad/s^2", gt=0
    )
    moving_obstacles: int = condition(
        0, "how many of a scene's obstacles move at constant velocity, bouncing in the scene's bounds", ge=0
    )
    obstacle_speed: float = condition(
        0.0, "speed of the moving obstacles (> 0 when moving_obstacles > 0)", unit="m/s", ge=0
    )

    def __post_init__(self) -> None:
        for name in CONDITION_FIELDS:
            _check_condition(name, getattr(self, name))
        if self.moving_obstacles > 0 and self.obstacle_speed == 0:
            raise ValueError(
                f"conditions: moving_obstacles={self.moving_obstacles} needs obstacle_speed > 0 [m/s], got 0"
            )

    @property
    def enabled(self) -> bool:
        """Any field not at its default."""
        return self != Conditions()

    def changed(self) -> dict:
        """The fields not at their default, by name (for results files and logs)."""
        off = Conditions()
        return {
            f.name: getattr(self, f.name)
            for f in fields(self)
            if getattr(self, f.name) != getattr(off, f.name)
        }


CONDITION_FIELDS = tuple(f.name for f in fields(Conditions))
# Each field's annotation, resolved: bool, int, float or float | None (what the env config's field and
# the CLI flag parse).
CONDITION_TYPES: dict[str, object] = typing.get_type_hints(Conditions)


def _kind(name: str) -> tuple[type, bool]:
    """(value type, None allowed) of condition ``name``, from its annotation."""
    annotation = CONDITION_TYPES[name]
    args = typing.get_args(annotation) or (annotation,)
    kinds = [t for t in args if t is not type(None)]
    if len(kinds) != 1 or kinds[0] not in (bool, int, float):
        raise TypeError(f"conditions: {name} must be declared bool, int, float or float | None")
    return kinds[0], type(None) in args


_FIELDS = {f.name: f for f in fields(Conditions)}
_KINDS = {name: _kind(name) for name in CONDITION_FIELDS}  # checked at import: a bad declaration fails


def condition_kind(name: str) -> type:
    """The value type of condition ``name``: ``bool``, ``int`` or ``float`` (None aside)."""
    return _KINDS[name][0]


def condition_help(name: str) -> str:
    """The help of condition ``name`` as the env config and the CLI flags show it: ``[unit] help``."""
    meta = _FIELDS[name].metadata
    return f"[{meta['unit']}] {meta['help']}" if meta["unit"] else meta["help"]


def _check_condition(name: str, value) -> None:
    """``ValueError`` naming the field and the value where ``value`` is not of condition ``name``'s
    kind or is outside its bounds (``condition``); None passes where the field allows it."""
    kind, optional = _KINDS[name]
    meta = _FIELDS[name].metadata
    if value is None and optional:
        return
    if kind is bool:
        if not isinstance(value, bool | np.bool_):
            raise ValueError(f"conditions: {name} must be true or false, got {value!r}")
        return
    gt, ge, le = meta["gt"], meta["ge"], meta["le"]
    low = f" > {gt}" if gt is not None else f" >= {ge}" if ge is not None else ""
    if kind is int:
        ok = isinstance(value, int | np.integer) and not isinstance(value, bool)
        what = "an integer"
    else:
        ok = isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool)
        ok = ok and math.isfinite(value)
        what = "a finite number"
    if not ok or (gt is not None and value <= gt) or (ge is not None and value < ge):
        raise ValueError(f"conditions: {name} must be {what}{low}, got {value!r}")
    if le is not None and value > le:
        unit = f" {meta['unit']}" if meta["unit"] else ""
        raise ValueError(f"conditions: {name} must be <= {le}{unit}, got {value}")


RANDOMIZE_TAG = 0x72616E64  # "rand": the draw of randomized conditions (``randomized_conditions``)
RANDOMIZE_ON = 0.6  # probability that each condition is on in a randomized draw


def randomized_conditions(ceiling: Conditions, key: int, p_on: float = RANDOMIZE_ON) -> Conditions:
    """One draw of conditions up to ``ceiling``'s severity, a pure function of (``ceiling``, ``key``,
    ``p_on``) (the stream ``episode_rng(key, RANDOMIZE_TAG)``).

    Each condition the ceiling has on is on with probability ``p_on``, independently, at a severity
    f ~ U(0, 1) of its own: noises (obstacle, pose, action) f x the ceiling's std; the sensing range
    and the rate limits (both limits together) (2 - f) x the ceiling's value (from twice as lax up
    to the ceiling's); the action delay 1 .. the ceiling's steps, uniform; moving obstacles 1 .. the
    ceiling's count, uniform, at (0.5 + 0.5 f) x its speed. ``obstacle_memory`` is the ceiling's.
    Every draw is made whatever the ceiling, so a field's draw does not depend on the others."""
    if not 0.0 <= p_on <= 1.0:
        raise ValueError(f"randomized conditions: p_on must be in [0, 1], got {p_on!r}")
    rng = episode_rng(int(key), RANDOMIZE_TAG)
    groups = ("sensing", "obstacle_noise", "pose_noise", "action_noise", "delay", "rate", "moving")
    on = dict(zip(groups, rng.uniform(size=len(groups)) < p_on, strict=True))
    f = dict(zip(groups, rng.uniform(size=len(groups)), strict=True))
    pick = dict(zip(groups, rng.uniform(size=len(groups)), strict=True))  # integer draws
    c = ceiling
    out: dict = {"obstacle_memory": c.obstacle_memory}
    if c.sensing_range is not None and on["sensing"]:
        out["sensing_range"] = c.sensing_range * (2.0 - f["sensing"])
    for name in ("obstacle_noise", "pose_noise", "action_noise"):
        if getattr(c, name) and on[name]:
            out[name] = getattr(c, name) * f[name]
    if c.action_delay and on["delay"]:
        out["action_delay"] = 1 + int(pick["delay"] * c.action_delay)
    if on["rate"]:
        for name in ("max_linear_accel", "max_angular_accel"):
            if getattr(c, name) is not None:
                out[name] = getattr(c, name) * (2.0 - f["rate"])
    if c.moving_obstacles and on["moving"]:
        out["moving_obstacles"] = 1 + int(pick["moving"] * c.moving_obstacles)
        out["obstacle_speed"] = c.obstacle_speed * (0.5 + 0.5 * f["moving"])
    return Conditions(**out)


@dataclass
class Perception:
    """What B teams perceive at one control step: all a controller under test gets.

    Attributes:
        pose: (B, 3) observed midpoint pose [x, y, phi] (noisy with ``pose_noise``).
        velocity: (B, 3) the midpoint velocity [x', y', omega] over the last control step.
        obstacles: (B, M, 3) observed obstacles [x, y, r]; unobserved slots (FAR, FAR, 0).
        mask: (B, M) bool, observed (and real) obstacles.
        obstacle_velocity: (B, M, 2) observed obstacles' velocities [m/s] (0: static or unobserved).
        goal: (B, 2) the goal.
        map_version: (B,) int64, incremented whenever the set of observed obstacles of a team changes:
            a controller caches what it derives from the map (a cost-to-go) by it.
        map_obstacles: (B, M, 3) the map a controller or the route hint builds its cost-to-go from:
            the observed static obstacles as observed (noisy) at the step ``map_version`` last
            changed, so it is constant between map changes; moving obstacles and unobserved slots
            are padding (FAR, FAR, 0). Without conditions it is ``obstacles``.
        scene_seed: (B,) int64 each team's scene seed (-1: a scene given by hand), or None: not an
            observation but the episode's name, which a controller keys its own random draws by
            (one stream per episode, so an episode's draws do not depend on the others in its batch).
    """

    pose: np.ndarray
    velocity: np.ndarray
    obstacles: np.ndarray
    mask: np.ndarray
    obstacle_velocity: np.ndarray
    goal: np.ndarray
    map_version: np.ndarray
    map_obstacles: np.ndarray
    scene_seed: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.pose)

    def __getitem__(self, idx) -> Perception:
        return Perception(
            self.pose[idx],
            self.velocity[idx],
            self.obstacles[idx],
            self.mask[idx],
            self.obstacle_velocity[idx],
            self.goal[idx],
            self.map_version[idx],
            self.map_obstacles[idx],
            None if self.scene_seed is None else self.scene_seed[idx],
        )

    @property
    def moving(self) -> bool:
        """Some observed obstacle moves."""
        return bool(np.any(self.obstacle_velocity))

    @staticmethod
    def exact(scenes: Scenes, state: FormationState) -> Perception:
        """The perception without conditions: the true scenes and state (arrays shared, not copied)."""
        B, M, _ = scenes.obstacles.shape
        return Perception(
            state.pose,
            state.velocity,
            scenes.obstacles,
            scenes.mask,
            np.zeros((B, M, 2)),
            scenes.goal,
            np.zeros(B, dtype=np.int64),
            scenes.obstacles,
            scenes.seeds,
        )


def episode_rng(seed: int, tag: int) -> np.random.Generator:
    """The generator of one episode's stream ``tag`` (``NOISE_TAG``, ``MOTION_TAG``)."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFFFFFF, tag])


def scene_bounds(scenes: Scenes) -> np.ndarray:
    """(B, 4) [x_lo, y_lo, x_hi, y_hi]: the box around a scene's real obstacles, start and goal plus
    ``BOUNDS_MARGIN``, inside which its moving obstacles' centres stay."""
    obs, mask = scenes.obstacles, scenes.mask
    lo_obs = np.where(mask[..., None], obs[..., :2] - obs[..., 2:3], np.inf).min(axis=1)
    hi_obs = np.where(mask[..., None], obs[..., :2] + obs[..., 2:3], -np.inf).max(axis=1)
    lo = np.minimum(np.minimum(lo_obs, scenes.start[:, :2]), scenes.goal) - BOUNDS_MARGIN
    hi = np.maximum(np.maximum(hi_obs, scenes.start[:, :2]), scenes.goal) + BOUNDS_MARGIN
    return np.concatenate([lo, hi], axis=1)


def _zones(scenes: Scenes) -> np.ndarray:
    """(B, 2, 2) the start and goal zone centres."""
    return np.stack([scenes.start[:, :2], scenes.goal], axis=1)


def obstacle_velocities(scenes: Scenes, conditions: Conditions) -> np.ndarray:
    """(B, M, 2) each obstacle's velocity [m/s] at the episode's start.

    A scene with its own ``velocities`` keeps them. Otherwise ``moving_obstacles`` of its real
    obstacles that start outside the start and goal zones (fewer if it has fewer) are chosen, and
    their directions drawn, by ``episode_rng(seed, MOTION_TAG)``; they move at ``obstacle_speed``.
    Only obstacles clear of every other real obstacle move (one that overlaps another is part of a
    wall or a cluster)."""
    B, M, _ = scenes.obstacles.shape
    vel = np.zeros((B, M, 2))
    given = scenes.velocities
    k = conditions.moving_obstacles
    zones = _zones(scenes)
    for b in range(B):
        if given is not None and np.any(given[b]):
            vel[b] = given[b]
            continue
        if k == 0:
            continue
        centre, r = scenes.obstacles[b, :, :2], scenes.obstacles[b, :, 2]
        gap = np.linalg.norm(centre[:, None] - zones[b][None], axis=-1) - r[:, None]  # (M, 2)
        apart = _pair_gaps(scenes.obstacles[b][None], scenes.mask[b][None])[0]  # (M, M), inf off-mask
        free = np.flatnonzero(scenes.mask[b] & (gap > ZONE_RADIUS).all(axis=1) & (apart > 0).all(axis=1))
        rng = episode_rng(scenes.seeds[b] if scenes.seeds[b] >= 0 else b, MOTION_TAG)
        chosen = rng.permutation(free)[:k]
        angle = rng.uniform(0.0, 2 * np.pi, size=len(chosen))
        vel[b, chosen] = conditions.obstacle_speed * np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    return vel


def _pair_gaps(obstacles: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(B, M, M) surface gaps |c_i - c_j| - r_i - r_j between the real obstacles (B, M, 3) of each
    scene; inf on the diagonal and for padding rows (mask (B, M) False)."""
    d = np.linalg.norm(obstacles[:, :, None, :2] - obstacles[:, None, :, :2], axis=-1)
    gap = d - obstacles[:, :, None, 2] - obstacles[:, None, :, 2]
    real = mask[:, :, None] & mask[:, None, :]
    real &= ~np.eye(obstacles.shape[1], dtype=bool)[None]
    return np.where(real, gap, np.inf)


def move_obstacles(
    obstacles: np.ndarray,
    velocity: np.ndarray,
    dt: float,
    bounds: np.ndarray,
    zones: np.ndarray,
    mask: np.ndarray | None = None,
) -> None:
    """Move obstacles (B, M, 3) by velocity (B, M, 2) over dt, in place, and bounce (in place too).

    Bounds (B, 4): a centre that leaves the box is reflected back into it and the velocity component
    flips. Zones (B, Z, 2): an obstacle whose surface comes within ``ZONE_RADIUS`` of a zone centre
    while moving toward it gets its velocity reflected about the line to that centre (and keeps its
    step's position: it turns at the edge). Other obstacles (the real ones of ``mask`` (B, M); None:
    every row): a mover whose step would overlap another obstacle keeps its position and reflects its
    velocity about the line of centres, v <- v - 2 (v . n) n with n the unit vector from the other
    obstacle to it, where it moves toward the other (v . n < 0; of two movers closing on each other at
    least one does); a mover is never moved into an overlap, so from a clear start none ever
    overlaps another obstacle."""
    moving = np.any(velocity != 0, axis=-1)  # (B, M)
    if not moving.any():
        return
    before = obstacles[..., :2].copy()
    xy = obstacles[..., :2] + velocity * dt
    for axis in range(2):
        lo, hi = bounds[:, axis][:, None], bounds[:, 2 + axis][:, None]
        below, above = xy[..., axis] < lo, xy[..., axis] > hi
        xy[..., axis] = np.where(
            below, 2 * lo - xy[..., axis], np.where(above, 2 * hi - xy[..., axis], xy[..., axis])
        )
        velocity[..., axis] = np.where(below | above, -velocity[..., axis], velocity[..., axis])
    xy = np.clip(xy, bounds[:, None, :2], bounds[:, None, 2:])
    for z in range(zones.shape[1]):
        rel = xy - zones[:, z][:, None]  # (B, M, 2)
        dist = np.linalg.norm(rel, axis=-1)
        normal = rel / np.maximum(dist, 1e-9)[..., None]
        toward = np.sum(velocity * normal, axis=-1)  # < 0: approaching the zone centre
        hit = moving & (dist - obstacles[..., 2] < ZONE_RADIUS) & (toward < 0)
        velocity[hit] -= 2 * toward[hit][:, None] * normal[hit]
        xy[hit] = obstacles[hit, :2]  # stay where it was this step, then leave along the new velocity
    xy = np.where(moving[..., None], xy, before)
    real = np.ones(moving.shape, dtype=bool) if mask is None else mask
    if (moving.sum(axis=1) > 0).any() and obstacles.shape[1] > 1:
        _bounce_off_obstacles(obstacles[..., 2], xy, before, velocity, moving & real, real)
    obstacles[..., :2] = xy


def _bounce_off_obstacles(
    radius: np.ndarray, xy: np.ndarray, before: np.ndarray, velocity: np.ndarray, moving, real
) -> None:
    """``move_obstacles``' contacts between obstacles, in place on the stepped centres ``xy`` and the
    velocities: each mover that overlaps another real obstacle after its step goes back to where it
    was (``before``, clear of every obstacle's position there) and reflects its velocity off that
    obstacle where it moved toward it. A mover put back can overlap another mover's new place, so the
    check repeats until nothing overlaps (at most M rounds: each round puts back at least one mover,
    and all put back is the clear start)."""
    obstacles = np.concatenate([xy, radius[..., None]], axis=-1)
    reflected = np.zeros(moving.shape, dtype=bool)
    for _ in range(moving.shape[1]):
        gap = _pair_gaps(obstacles, real)  # (B, M, M)
        contact = (gap < 0) & moving[:, :, None]
        stepped = np.any(xy != before, axis=-1)  # only a mover that moved this step goes back
        contact &= stepped[:, :, None]
        if not contact.any():
            return
        b, i, j = np.nonzero(contact)
        n = before[b, i] - obstacles[b, j, :2]  # from the other obstacle to the mover, at its old place
        n /= np.maximum(np.linalg.norm(n, axis=-1), 1e-9)[:, None]
        toward = np.sum(velocity[b, i] * n, axis=-1)
        for k in np.flatnonzero(toward < 0):  # one reflection per mover and step, off its first contact
            if not reflected[b[k], i[k]]:
                velocity[b[k], i[k]] -= 2 * toward[k] * n[k]
                reflected[b[k], i[k]] = True
        xy[b, i] = before[b, i]
        obstacles[b, i, :2] = before[b, i]


class ConditionedWorld:
    """The conditions' state of B teams, held by ``core.episodes.rollout.Teams`` (which keeps the true scenes
    and state): what each team has seen, its noise stream, its command FIFO and executed velocity,
    and its obstacles' velocities.

    Args:
        conditions: the conditions.
        scenes: the teams' scenes (the Teams' own copy: moving obstacles move in it).
        state: the teams' state at their start.
        params: the formation parameters (dt, bounds, agent radius).
    """

    def __init__(
        self, conditions: Conditions, scenes: Scenes, state: FormationState, params: FormationParams
    ):
        self.conditions = conditions
        self.params = params
        B, M, _ = scenes.obstacles.shape
        self.seen = np.zeros((B, M), dtype=bool)  # observed now (with memory: ever)
        self.seen_step = np.full((B, M), -1, dtype=np.int64)
        self.map_version = np.zeros(B, dtype=np.int64)
        self.map_obstacles = np.zeros((B, M, 3))  # Perception.map_obstacles, taken by ``perceive``
        self.map_taken = np.full(B, -1, dtype=np.int64)  # the map_version map_obstacles was taken at
        self.queue = np.zeros((B, conditions.action_delay, 2))
        self.executed = np.zeros((B, 2))  # the velocity applied over the last step (rate limits)
        self.velocity = np.zeros((B, M, 2))
        self.bounds = np.zeros((B, 4))
        self.zones = np.zeros((B, 2, 2))
        self.noise = np.zeros((B, 5 + 3 * M))
        self.real = np.zeros((B, M), dtype=bool)  # the scenes' real obstacles (mask)
        self.rngs: list[np.random.Generator | None] = [None] * B
        self.load(np.arange(B), scenes, state)

    def load(self, idx: np.ndarray, scenes: Scenes, state: FormationState) -> None:
        """(Re)start the teams ``idx`` in ``scenes`` (one per index, already in the Teams' arrays) at
        ``state`` (their start)."""
        idx = np.asarray(idx)
        self.seen[idx] = False
        self.seen_step[idx] = -1
        self.map_version[idx] = 0
        self.map_taken[idx] = -1
        self.queue[idx] = 0.0
        self.executed[idx] = 0.0
        self.velocity[idx] = obstacle_velocities(scenes, self.conditions)
        self.bounds[idx] = scene_bounds(scenes)
        self.zones[idx] = _zones(scenes)
        for i, seed in zip(idx, scenes.seeds, strict=True):
            self.rngs[i] = episode_rng(int(seed) if seed >= 0 else int(i), NOISE_TAG)
        self.real[idx] = scenes.mask
        self.sense(idx, scenes.obstacles, state, np.zeros(len(idx), dtype=np.int64))
        self.draw(idx)

    # the arrays with one row per team (``rngs`` too, a list)
    PER_TEAM = (
        "seen",
        "seen_step",
        "map_version",
        "map_obstacles",
        "map_taken",
        "queue",
        "executed",
        "velocity",
        "bounds",
        "zones",
        "noise",
        "real",
    )

    def keep(self, rows) -> None:
        """Keep only the teams ``rows`` (an index or mask), in that order."""
        for name in self.PER_TEAM:
            setattr(self, name, getattr(self, name)[rows])
        self.rngs = [self.rngs[i] for i in np.arange(len(self.rngs))[rows]]

    @classmethod
    def gather(cls, parts: list[tuple[ConditionedWorld, np.ndarray]]) -> ConditionedWorld:
        """A new world of the teams ``rows`` of each (world, rows) part (index arrays, repeats allowed),
        in that order, every noise stream copied where it stands (the worlds share their conditions)."""
        out = copy.copy(parts[0][0])
        for name in cls.PER_TEAM:
            setattr(out, name, np.concatenate([getattr(world, name)[rows] for world, rows in parts]))
        out.rngs = [copy.deepcopy(world.rngs[i]) for world, rows in parts for i in rows]
        return out

    # -- per step ---------------------------------------------------------------------------------
    def sense(self, idx, obstacles: np.ndarray, state: FormationState, steps: np.ndarray) -> None:
        """Update what the teams ``idx`` observe at their state (teams ``idx`` of ``state``): obstacles
        (len(idx), M, 3) are their true obstacles, ``steps`` their control steps."""
        real = self.real[idx]
        r = self.conditions.sensing_range
        if r is None:
            now = real
        else:
            gaps = obstacle_gaps(agent_positions(state), obstacles)  # (b, N, M) agent centre to surface
            now = real & (gaps.min(axis=1) <= r)
        old = self.seen[idx]
        new = now | old if self.conditions.obstacle_memory else now
        first = new & (self.seen_step[idx] < 0)
        self.seen_step[idx] = np.where(first, steps[:, None], self.seen_step[idx])
        self.map_version[idx] += (new != old).any(axis=1)
        self.seen[idx] = new

    def draw(self, idx) -> None:
        """Draw the next control step's noise of the teams ``idx``: one vector per team from its own
        stream (pose 3, action 2, then 3 per real obstacle of its scene)."""
        for i in np.arange(len(self.seen))[idx]:
            m = int(self.real[i].sum())
            z = self.rngs[i].standard_normal(5 + 3 * m)
            self.noise[i, : 5 + 3 * m] = z

    def execute(self, command: np.ndarray) -> np.ndarray:
        """The velocity (B, 2) each team executes this step for its ``command`` (B, 2): delayed,
        noisy, clipped to the bounds, then rate limited (``dynamics.rate_limit``)."""
        c, p = self.conditions, self.params
        if c.action_delay:
            out = self.queue[:, 0].copy()
            self.queue[:, :-1] = self.queue[:, 1:]
            self.queue[:, -1] = command
        else:
            out = np.array(command, dtype=np.float64)
        if c.action_noise:
            out = out * (1.0 + c.action_noise * self.noise[:, 3:5])
        out = clip_action(out, p)
        if c.max_linear_accel is not None or c.max_angular_accel is not None:
            out = rate_limit(self.executed, out, c.max_linear_accel, c.max_angular_accel, p.dt)
        self.executed = out
        return out

    def move(self, obstacles: np.ndarray) -> None:
        """Move the teams' true obstacles (B, M, 3) one control step, in place."""
        move_obstacles(obstacles, self.velocity, self.params.dt, self.bounds, self.zones, self.real)

    def privileged(self, state: FormationState, scenes: Scenes) -> Perception:
        """The true world of the teams (what a privileged expert acts on; ``Perception.exact`` without
        conditions): the true pose and velocity, every real obstacle at its true current position
        (mask: the real ones) with its true velocity, and a static map of the true static obstacles
        (moving ones are padding: avoided by position and velocity, not by a stale wall) whose
        ``map_version`` stays 0, so a controller builds its cost-to-go once. Static obstacles never
        move and a moving one never stops (a bounce flips its velocity), so the map is constant."""
        static = self.real & ~np.any(self.velocity != 0, axis=-1)  # (B, M)
        pad = np.array([FAR, FAR, 0.0])
        return Perception(
            state.pose,
            state.velocity,
            np.where(self.real[..., None], scenes.obstacles, pad),
            self.real.copy(),
            self.velocity.copy(),
            scenes.goal,
            np.zeros(len(self.real), dtype=np.int64),
            np.where(static[..., None], scenes.obstacles, pad),
            scenes.seeds,
        )

    def perceive(self, state: FormationState, scenes: Scenes) -> Perception:
        """What the teams perceive now (``Perception``), from their true state and scenes. A team whose
        ``map_version`` changed since its last map snapshot gets a new one (``Perception.map_obstacles``)
        from this perception: the env and the engine perceive at every step, so it is the step's own."""
        c = self.conditions
        B, M, _ = scenes.obstacles.shape
        pose = state.pose
        if c.pose_noise:
            pose = pose + c.pose_noise * self.noise[:, :3]
        obstacles = np.where(self.seen[..., None], scenes.obstacles, np.array([FAR, FAR, 0.0]))
        if c.obstacle_noise:
            # the k-th real obstacle of a scene (in row order) takes the draws 5 + 3k .. 7 + 3k
            k = np.maximum(np.cumsum(self.real, axis=1) - 1, 0)  # (B, M)
            cols = 5 + 3 * k[..., None] + np.arange(3)  # (B, M, 3)
            z = np.take_along_axis(self.noise, cols.reshape(B, -1), axis=1).reshape(B, M, 3)
            noisy = obstacles + c.obstacle_noise * z
            noisy[..., 2] = np.maximum(noisy[..., 2], MIN_OBSERVED_RADIUS)
            obstacles = np.where(self.seen[..., None], noisy, obstacles)
        velocity = np.where(self.seen[..., None], self.velocity, 0.0)
        retake = self.map_taken != self.map_version  # the map changed since its last snapshot
        if retake.any():
            static = ~np.any(velocity[retake] != 0, axis=-1)  # moving obstacles stay off the map
            self.map_obstacles[retake] = np.where(
                static[..., None], obstacles[retake], np.array([FAR, FAR, 0.0])
            )
            self.map_taken[retake] = self.map_version[retake]
        return Perception(
            pose,
            state.velocity,
            obstacles,
            self.seen.copy(),
            velocity,
            scenes.goal,
            self.map_version.copy(),
            self.map_obstacles.copy(),
            scenes.seeds,
        )
