"""Path-Aware Controller (PAC): the demonstrator (paper Sec. V-A, SPEC "The demonstrator").

An artificial potential field for the leaders' midpoint, batched over B scenes:

1. attraction: unit vector toward the goal;
2. repulsion: for every obstacle within ``influence`` of the midpoint's inflated clearance rho,
   k_rep (1/rho - 1/influence) / rho^2 along the outward normal (Khatib's field);
3. path check: the segment from the midpoint toward the goal (up to ``lookahead`` metres) is blocked
   when it passes within r + ``inflate`` of an obstacle centre. Then a sideways force along the
   tangent of that inflated circle replaces the attraction, so the team detours instead of backing
   off. The side is kept while the same obstacle blocks (hysteresis against dithering);
4. the force becomes [v, omega]: omega = k_omega * wrap(theta_F - phi), v = v_cruise cos^2 of the
   heading error, slowed near the goal;
5. footprint governor: the whole formation, not just the midpoint, must stay clear. A small grid of
   (v, omega) candidates around the field's command is rolled out ``horizon`` steps with the rigid
   formation template (the followers' rear corners swing out to 1.12 m when the team turns); the
   candidate closest to the field's command whose footprint keeps ``safety_margin`` wins. If none
   does, the one with the largest predicted clearance wins.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lerobot_formation.core.controllers.footprint import template_clearance
from lerobot_formation.core.controllers.protocol import map_obstacles
from lerobot_formation.core.perception.conditions import Perception
from lerobot_formation.core.perception.obstacle_tracker import predict_obstacles
from lerobot_formation.core.world.dynamics import FormationParams, constant_action_poses, rollout_poses
from lerobot_formation.core.world.navigation import (
    PAC_CARROT_CELLS,
    PAC_INFLATE,
    PAC_LOOKAHEAD,
    PAC_PATH_INFLATE,
    SceneFields,
    path_blocked,
)
from lerobot_formation.core.world.scenes import FAR


@dataclass(frozen=True)
class PACConfig:
    v_cruise: float = 0.5  # [m/s]
    k_omega: float = 2.0  # [1/s] heading gain
    k_rep: float = 0.05  # repulsion gain
    influence: float = 0.5  # [m] repulsion range beyond the inflated radius
    # PAC's route, which the route hint plans too (``core.world.navigation``: the values and what they are)
    inflate: float = PAC_INFLATE  # [m] obstacle inflation: bar half-width + agent radius + margin
    lookahead: float = PAC_LOOKAHEAD  # [m] path-blocked check length
    path_inflate: float = PAC_PATH_INFLATE  # [m] obstacle inflation of the cost-to-go
    carrot_cells: int = PAC_CARROT_CELLS  # detour target: cost-to-go cells down the gradient
    goal_slow_radius: float = 1.0  # [m] slow down inside this distance to the goal
    horizon: int = 8  # footprint prediction steps (x dt)
    safety_margin: float = 0.08  # [m] predicted agent clearance to keep
    v_scales: tuple[float, ...] = (1.0, 0.5, 0.0)  # x the field's v, plus x v_cruise
    omega_offsets: tuple[float, ...] = (0.0, -0.5, 0.5)  # + the field's omega
    omega_fixed: tuple[float, ...] = (-1.5, -0.75, 0.0, 0.75, 1.5)  # absolute candidates [rad/s]


def wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def swept_obstacles(
    obstacles: np.ndarray, velocity: np.ndarray, lead: float, lookahead: float, spacing: float = 0.2
) -> np.ndarray:
    """The obstacles a predicting PAC avoids, obstacles (B, M, 3) with velocities (B, M, 2) [m/s] ->
    (B, M + K m, 3): every obstacle moved ``lead`` seconds along its velocity (static ones stay), then
    for the m slots that move in some row, K = ceil(lookahead / spacing) discs of the same radius at
    lead + j lookahead / K, j = 1..K, seconds ahead: the capsule a moving obstacle sweeps over the
    next ``lookahead`` seconds, as discs (straight on: a bounce is not predicted). Rows where such a
    slot does not move get padding (far away, radius 0). No moving obstacle: ``obstacles`` itself."""
    moving = np.any(velocity != 0, axis=-1)  # (B, M)
    if not moving.any():
        return obstacles
    now = predict_obstacles(np.asarray(obstacles, dtype=np.float64), velocity, [lead])[:, 0]
    k = int(np.ceil(lookahead / spacing)) if lookahead > 0 else 0
    if k == 0:
        return now
    cols = np.flatnonzero(moving.any(axis=0))
    times = lookahead * np.arange(1, k + 1) / k  # (K,)
    ahead = predict_obstacles(now[:, cols], velocity[:, cols], times)  # (B, K, m, 3)
    ahead = np.where(moving[:, None, cols, None], ahead, np.array([FAR, FAR, 0.0]))
    return np.concatenate([now, ahead.reshape(len(now), -1, 3)], axis=1)


class PathAwareController:
    """Batched PAC. ``reset(obstacles, goal)`` once per batch of episodes, then
    ``command(pose) -> (B, 2)`` every control step."""

    def __init__(self, config: PACConfig | None = None, params: FormationParams | None = None):
        self.config = config or PACConfig()
        self.params = params or FormationParams()
        self.template = np.asarray(self.params.graph.template)  # (N, 2)
        c = self.config
        n_w = len(c.omega_offsets) + len(c.omega_fixed)
        n_v = 2 * len(c.v_scales)
        # Candidate k: v = v_field * vs_rel[k] + v_cruise * vs_abs[k]; omega = omega_field * ws_rel[k] + ws_abs[k].
        vs_rel = np.concatenate([np.asarray(c.v_scales), np.zeros(len(c.v_scales))])
        vs_abs = np.concatenate([np.zeros(len(c.v_scales)), np.asarray(c.v_scales)])
        ws_rel = np.concatenate([np.ones(len(c.omega_offsets)), np.zeros(len(c.omega_fixed))])
        ws_abs = np.concatenate([np.asarray(c.omega_offsets), np.asarray(c.omega_fixed)])
        self._vs_rel, self._vs_abs = np.repeat(vs_rel, n_w), np.repeat(vs_abs, n_w)  # (C,)
        self._ws_rel, self._ws_abs = np.tile(ws_rel, n_v), np.tile(ws_abs, n_v)

    def reset(self, obstacles: np.ndarray, goal: np.ndarray) -> None:
        self.obstacles = np.asarray(obstacles, dtype=np.float64)
        self.goal = np.asarray(goal, dtype=np.float64)
        # one field per scene: a scene's demonstration must not depend on the other scenes of its batch
        self.ctg = SceneFields.build(self.obstacles, self.goal, inflate=self.config.path_inflate)

    def select(self, idx: np.ndarray) -> PathAwareController:
        """A view of this controller restricted to the episodes ``idx``."""
        sub = PathAwareController.__new__(PathAwareController)
        sub.__dict__.update(self.__dict__)
        sub.obstacles, sub.goal, sub.ctg = self.obstacles[idx], self.goal[idx], self.ctg[idx]
        return sub

    def field_command(
        self, pose: np.ndarray, velocity: np.ndarray | None = None, lookahead: float = 0.0
    ) -> np.ndarray:
        """Potential-field command (B, 2) before the footprint governor; with the obstacles'
        ``velocity`` (B, M, 2), moving ones are avoided along the capsule they sweep over the next
        ``lookahead`` seconds (``swept_obstacles``)."""
        c = self.config
        p, phi = pose[:, :2], pose[:, 2]
        obs = self.obstacles
        if velocity is not None and lookahead > 0:
            obs = swept_obstacles(obs, velocity, 0.0, lookahead)
        to_goal = self.goal - p
        dist_goal = np.linalg.norm(to_goal, axis=-1)
        u = to_goal / np.maximum(dist_goal, 1e-9)[:, None]  # (B, 2)
        blocked = path_blocked(p, self.goal, obs, c.lookahead, c.inflate)
        rel = obs[..., :2] - p[:, None, :]  # (B, M, 2)
        R = obs[..., 2] + c.inflate
        # Blocked: detour sideways toward the cost-to-go carrot, which picks the side that leads on.
        self.blocked = blocked
        attract = u
        if blocked.any():
            carrot = self.ctg.carrot(p, self.config.carrot_cells) - p
            carrot /= np.maximum(np.linalg.norm(carrot, axis=-1), 1e-9)[:, None]
            attract = np.where(blocked[:, None], carrot, u)
        # Repulsion (Khatib) from the inflated obstacles near the midpoint.
        dist_c = np.linalg.norm(rel, axis=-1)
        rho = np.maximum(dist_c - R, 0.05)
        mag = np.where(rho < c.influence, c.k_rep * (1 / rho - 1 / c.influence) / rho**2, 0.0)
        normal = -rel / np.maximum(dist_c, 1e-9)[..., None]
        repel = np.sum(mag[..., None] * normal, axis=1)
        force = attract + repel
        theta = np.arctan2(force[:, 1], force[:, 0])
        err = wrap(theta - phi)
        omega = np.clip(c.k_omega * err, -self.params.omega_max, self.params.omega_max)
        v = c.v_cruise * np.maximum(np.cos(err), 0.0) ** 2
        v = v * np.clip(dist_goal / c.goal_slow_radius, 0.3, 1.0)
        return np.stack([v, omega], axis=-1)

    def footprint_clearance(
        self,
        pose: np.ndarray,
        cand: np.ndarray,
        velocity: np.ndarray | None = None,
        lookahead: float = 0.0,
    ) -> np.ndarray:
        """Minimum predicted agent clearance over the horizon for candidates cand (B, C, 2) -> (B, C).
        With the obstacles' ``velocity`` (B, M, 2), a moving obstacle is checked where it will be at
        each predicted step k (its position + k dt velocity), the footprint at that same step, over
        the horizon or ``lookahead`` seconds if longer (one that will arrive in 1.5 s is not escaped
        by waiting)."""
        c = self.config
        r = self.params.agent_radius
        moving = None if velocity is None else np.any(velocity != 0, axis=-1)  # (B, M)
        if moving is None or not moving.any():
            poses = constant_action_poses(pose, cand, self.params.dt, c.horizon)  # (B, C, T, 3)
            return template_clearance(poses, self.obstacles, self.template, r).min(axis=-1)
        steps = max(c.horizon, int(np.ceil(lookahead / self.params.dt - 1e-9)))
        poses = constant_action_poses(pose, cand, self.params.dt, steps)
        pad = np.array([FAR, FAR, 0.0])
        static = np.where(moving[..., None], pad, self.obstacles)
        clear = template_clearance(poses[:, :, : c.horizon], static, self.template, r)
        B, C, T, _ = poses.shape
        cols = np.flatnonzero(moving.any(axis=0))
        ahead = np.repeat(self.obstacles[:, None, cols], T, axis=1)  # (B, T, m, 3)
        ahead[..., :2] += (
            velocity[:, None, cols] * (self.params.dt * np.arange(1, T + 1))[None, :, None, None]
        )
        ahead = np.where(moving[:, None, cols, None], ahead, pad)
        at_step = template_clearance(  # one batch row per (team, step): the footprints of that step
            poses.transpose(0, 2, 1, 3).reshape(B * T, C, 3), ahead.reshape(B * T, -1, 3), self.template, r
        )
        return np.minimum(clear.min(axis=-1), at_step.reshape(B, T, C).min(axis=1))

    def command(
        self, pose: np.ndarray, velocity: np.ndarray | None = None, lookahead: float = 0.0
    ) -> np.ndarray:
        """[v, omega] for B midpoint poses (B, 3) -> (B, 2). With the obstacles' ``velocity``
        (B, M, 2) the field avoids the moving ones' swept capsules over ``lookahead`` seconds and the
        governor checks them where they will be at each step (``footprint_clearance``); None: every
        obstacle is taken as static where it is."""
        desired = self.field_command(pose, velocity, lookahead)
        v = desired[:, None, 0] * self._vs_rel + self.config.v_cruise * self._vs_abs
        w = desired[:, None, 1] * self._ws_rel + self._ws_abs
        cand = np.stack([v, np.clip(w, -self.params.omega_max, self.params.omega_max)], axis=-1)  # (B, C, 2)
        clear = self.footprint_clearance(pose, cand, velocity, lookahead)
        safe = clear >= self.config.safety_margin
        dev = (cand[..., 0] - desired[:, None, 0]) ** 2 + 0.1 * (cand[..., 1] - desired[:, None, 1]) ** 2
        score = np.where(safe, dev, np.inf)
        best = np.argmin(score, axis=1)
        fallback = np.argmax(clear, axis=1)
        pick = np.where(safe.any(axis=1), best, fallback)
        return cand[np.arange(len(pose)), pick]


class PACController:
    """PAC behind the common controller interface, on what the team perceives.

    The cost-to-go (PAC's detour side) is built per team from ``map_obstacles`` of its perception
    when the episode starts and rebuilt for a team only when its ``map_version`` changes (a new
    obstacle sensed, or one forgotten): with noise it is the noisy snapshot of that moment, the same
    map the route hint (``core.encodings.route_encoding``) plans on. The repulsion, the path check and the
    footprint governor use the current (noisy, moving) observed obstacles at every step.

    Args:
        predict: [s] lookahead for moving obstacles: each one is also avoided at its positions over
            the next ``predict`` seconds along its observed velocity (``pac.swept_obstacles``); 0: at
            its current position only.
        delay: [control steps] command delay to compensate: PAC acts for the pose its last ``delay``
            commands (still queued, ``Conditions.action_delay``) will reach, and for the moving
            obstacles ``delay`` steps ahead; 0: none. The two defaults leave PAC as it was.
    """

    name = "pac"

    def __init__(
        self,
        config: PACConfig | None = None,
        params: FormationParams | None = None,
        predict: float = 0.0,
        delay: int = 0,
    ):
        if not isinstance(predict, int | float) or not np.isfinite(predict) or predict < 0:
            raise ValueError(
                f"PACController: predict must be a finite number of seconds >= 0, got {predict!r}"
            )
        if not isinstance(delay, int | np.integer) or isinstance(delay, bool) or delay < 0:
            raise ValueError(f"PACController: delay must be an integer number of steps >= 0, got {delay!r}")
        self.pac = PathAwareController(config, params)
        self.predict = float(predict)
        self.delay = int(delay)

    def reset(self, view: Perception) -> None:
        self.pac.reset(map_obstacles(view), view.goal)
        self.version = np.array(view.map_version, copy=True)
        self.sent = np.zeros((len(view), self.delay, 2))  # queued commands, oldest first (delay)

    def act(self, view: Perception, idx: np.ndarray) -> np.ndarray:
        idx = np.asarray(idx)
        changed = view.map_version != self.version[idx]
        if changed.any():
            rows = idx[changed]
            fresh = SceneFields.build(
                map_obstacles(view[changed]), view.goal[changed], self.pac.config.path_inflate
            )
            for i, field in zip(rows, fresh.fields, strict=True):
                self.pac.ctg.fields[i] = field
            self.version[rows] = view.map_version[changed]
        sub = self.pac.select(idx)
        pose, obstacles = view.pose, view.obstacles
        dt = self.pac.params.dt
        if self.delay:  # the pose once the queued commands have run, the moving obstacles then
            pose = rollout_poses(pose, self.sent[idx][:, None], dt)[:, 0, -1]
            obstacles = swept_obstacles(obstacles, view.obstacle_velocity, self.delay * dt, 0.0)
        sub.obstacles = obstacles
        if self.predict:
            command = sub.command(pose, view.obstacle_velocity, self.predict)
        else:
            command = sub.command(pose)
        if self.delay:
            self.sent[idx] = np.concatenate([self.sent[idx][:, 1:], command[:, None]], axis=1)
        return command
