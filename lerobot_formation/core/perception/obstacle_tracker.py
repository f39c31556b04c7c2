"""Moving obstacles for the safety layer: constant-velocity prediction, and a tracker that estimates
the observed obstacles' velocities from the ``nearest`` observation alone.

Prediction (``predict_obstacles``): an obstacle [x, y, r] with velocity [vx, vy] is at
[x + vx t, y + vy t, r] t seconds later. All in the midpoint's body frame at the current step. With an
``uncertainty`` u [m/s] a moving obstacle's predicted radius grows as r + u t min(1, |v| / MOVING_SPEED):
a constant-velocity prediction drifts from the truth with the estimate's velocity error and with any
turn the obstacle makes (a bounce), more the further ahead it looks; an obstacle estimated at rest
(every static one, within the estimate's noise) keeps its radius, its prediction being exact.

Tracking (``ObstacleTracker``). The ``nearest`` encoding gives the goal g_b and the obstacles o_b in
the body frame of the observed (noisy) pose (p, a = phi - pi/2): o_b = R(-a)(o - p), g_b = R(-a)(g - p).
Relative to the goal, q = o_b - g_b = R(-a)(o - g): the pose's position (and its noise) cancels, and
since the goal is fixed and exact, a static obstacle's q changes from one step to the next only by
the rotation D = -(a_t - a_{t-1}) of the observed heading (heading noise included) and its own
observation noise: q_t = R(D) q_{t-1}. So the tracker works on q and estimates one angle per step:

1. prior: the change of the goal's bearing, angle(g_b,t) - angle(g_b,t-1) = D + e, where
   |e| <= (the observed position's change) / |g_b|;
2. search: ``search_angles`` angles within +-w of the prior, w = clip(``reach`` / |g_b|, 0.02, 0.5)
   rad, minimising the robust matching cost sum_j min(min_k |q_j - R(D) p_k|^2 + (r_j - r_k)^2, gate^2)
   between the observed obstacles (q_j, radius r_j) and the tracks' predictions p_k = x_k + v_k dt;
3. association: mutual nearest neighbours at that angle, within ``gate``;
4. refinement: the least-squares rotation about the goal of the associated pairs,
   D = atan2(sum p_k x q_j, sum p_k . q_j);
5. update: a constant-velocity Kalman filter per track and axis (state [x, v], process noise of
   ``speed_change`` m/s per step on v, measurement noise ``noise`` m, prior speed std
   ``prior_speed``): with the residual r = q_j - R(D)(x_k + v_k dt),
   x <- R(D)(x_k + v_k dt) + K0 r,  v <- R(D) v_k + K1 r.
   Every track shares the model, so the gains depend on the track's age alone (``kalman_gains``,
   computed once); the covariance is isotropic, so the rotation leaves it as it is;
6. anchoring: velocities that all turn about the goal at one rate w, v_j + w (-q_jy, q_jx), predict
   every track rotated by w dt, which step 4 takes for a heading change: that error is never seen
   and, once made (a moving obstacle's first steps bias D), stays. Most obstacles stand still, so
   the median of the tracks' rates (q_j x v_j) / |q_j|^2 is taken as that error and subtracted. With
   one observed obstacle its motion across the line to the goal is not observable (it comes out 0);
   with two, half of a moving one's rate goes to the other.

An observed obstacle without a match starts a track at rest (velocity 0); a track whose obstacle is
not observed any more is dropped. q has the body frame's axes, so the velocities are the obstacles'
velocities in the current body frame, as the ``nearest+velocity`` encoding gives them. A static
obstacle comes out at ~0 (the estimate's noise falls as 1 / age^1.5 to a floor set by
``speed_change``), a moving one at its velocity after ~1 s (10 steps).
"""

from __future__ import annotations

import functools

import numpy as np

MOVING_SPEED = 0.1  # [m/s] an estimated speed from which an obstacle's prediction gets the whole uncertainty


def predict_obstacles(
    obstacles: np.ndarray, velocity: np.ndarray, times: np.ndarray, uncertainty: float = 0.0
) -> np.ndarray:
    """Obstacles (B, M, 3) moving at ``velocity`` (B, M, 2), at ``times`` (T,) seconds from now ->
    (B, T, M, 3): centres + velocity * t; radii unchanged, or with ``uncertainty`` u [m/s] grown by
    u t min(1, |velocity| / ``MOVING_SPEED``) (module docstring)."""
    times = np.asarray(times, dtype=np.float64)
    out = np.repeat(obstacles[:, None], len(times), axis=1)
    out[..., :2] += velocity[:, None] * times[None, :, None, None]
    if uncertainty:
        moving = np.minimum(1.0, np.linalg.norm(velocity, axis=-1) / MOVING_SPEED)  # (B, M)
        out[..., 2] += uncertainty * times[None, :, None] * moving[:, None, :]
    return out


@functools.cache
def kalman_gains(
    dt: float, noise: float, prior_speed: float, speed_change: float, steps: int = 100
) -> np.ndarray:
    """Gains (steps + 1, 2) [K0, K1] of the n-th measurement (row n - 1) of a track: the Kalman filter
    of x_{k+1} = x_k + v_k dt, v_{k+1} = v_k + w (w ~ N(0, speed_change^2)), z = x + n
    (n ~ N(0, noise^2)), started at the first measurement with P = diag(noise^2, prior_speed^2)
    (row 0 = [1, 0]: the position is the measurement, the velocity 0). The last row is (nearly) the
    steady state and serves every older track."""
    F = np.array([[1.0, dt], [0.0, 1.0]])
    Q = np.diag([0.0, speed_change**2])
    P = np.diag([noise**2, prior_speed**2])
    gains = [np.array([1.0, 0.0])]
    for _ in range(steps):
        P = F @ P @ F.T + Q
        K = P[:, 0] / (P[0, 0] + noise**2)
        P = P - np.outer(K, P[0])
        gains.append(K)
    table = np.array(gains)
    table.flags.writeable = False
    return table


def _rotate(angle_cos: np.ndarray, angle_sin: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """R(angle) applied to xy (..., 2); cos and sin broadcast against (...)."""
    x, y = xy[..., 0], xy[..., 1]
    return np.stack([angle_cos * x - angle_sin * y, angle_sin * x + angle_cos * y], axis=-1)


def _masked_median(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Median (b,) of ``values`` (b, S) where ``mask`` (b, S); 0 for a row without any."""
    k = mask.sum(-1)
    ordered = np.sort(np.where(mask, values, np.inf), axis=-1)
    lo = np.take_along_axis(ordered, (np.maximum(k - 1, 0) // 2)[:, None], axis=-1)[:, 0]
    hi = np.take_along_axis(ordered, np.minimum(k // 2, values.shape[1] - 1)[:, None], axis=-1)[:, 0]
    return np.where(k > 0, 0.5 * (lo + hi), 0.0)  # k = 0: inf, replaced


class ObstacleTracker:
    """Per-episode velocity estimates of the observed obstacles of B episodes (module docstring).

    Args:
        batch_size: B episodes.
        slots: obstacle slots of the observation (S).
        dt: control period [s].
        noise: the observed centres' noise std [m] the filter assumes.
        prior_speed: std [m/s] of a new track's velocity (a new track starts at rest).
        speed_change: std [m/s] of a track's velocity change per step (bounces, turns).
        gate: [m] the largest distance (centre and radius) at which an observation continues a track.
        reach: [m] the largest change of the observed position per step (w of the angle search).
        search_angles: angles of the search.
    """

    def __init__(
        self,
        batch_size: int,
        slots: int,
        dt: float,
        noise: float = 0.05,
        prior_speed: float = 0.3,
        speed_change: float = 0.01,
        gate: float = 0.35,
        reach: float = 0.3,
        search_angles: int = 25,
    ):
        if batch_size < 0 or slots < 1:
            raise ValueError(f"need batch_size >= 0 and slots >= 1, got {batch_size} and {slots}")
        for name, value in (("dt", dt), ("noise", noise), ("gate", gate), ("reach", reach)):
            if not value > 0:
                raise ValueError(f"{name} must be > 0, got {value}")
        self.dt, self.gate, self.reach = dt, gate, reach
        self.gains = kalman_gains(dt, noise, prior_speed, speed_change)
        self.steps = np.linspace(-1.0, 1.0, search_angles)
        self.position = np.zeros((batch_size, slots, 2))  # x_k, goal-relative (q), last step's frame
        self.velocity = np.zeros((batch_size, slots, 2))  # v_k, last step's body axes
        self.radius = np.zeros((batch_size, slots))
        self.age = np.zeros((batch_size, slots), dtype=np.int64)  # measurements; 0: no track
        self.goal = np.zeros((batch_size, 2))  # last step's goal in the body frame
        self.started = np.zeros(batch_size, dtype=bool)

    def reset(self, rows=None) -> None:
        """Forget the tracks of episodes ``rows`` (default all): their next update starts afresh."""
        rows = slice(None) if rows is None else rows
        self.age[rows] = 0
        self.velocity[rows] = 0.0
        self.started[rows] = False

    def update(self, goal: np.ndarray, obstacles: np.ndarray, mask: np.ndarray, rows=None) -> np.ndarray:
        """Take the current observation of episodes ``rows`` (default all): goal (b, 2), obstacles
        (b, S, 3) and mask (b, S) in the body frame (``safety.decode_nearest``) -> the observed
        obstacles' velocities (b, S, 2) [m/s] in the body frame (0 for empty slots and new tracks)."""
        rows = np.arange(len(self.age)) if rows is None else np.asarray(rows)
        goal = np.asarray(goal, dtype=np.float64)
        obstacles = np.asarray(obstacles, dtype=np.float64)
        b, S = mask.shape
        if obstacles.shape != (b, S, 3) or goal.shape != (b, 2) or len(rows) != b or S != self.age.shape[1]:
            raise ValueError(
                f"update needs goal (b, 2), obstacles (b, {self.age.shape[1]}, 3), mask (b, "
                f"{self.age.shape[1]}) and b rows, got {goal.shape}, {obstacles.shape}, {mask.shape}, {len(rows)}"
            )
        q, radius = obstacles[..., :2] - goal[:, None], obstacles[..., 2]
        age = np.where(self.started[rows, None], self.age[rows], 0)
        alive = age > 0
        predicted = self.position[rows] + self.velocity[rows] * self.dt  # p_k, last step's frame
        # 1-2: the rotation D between the frames, from the goal's bearing and a matching search
        prior = np.angle((goal[:, 0] + 1j * goal[:, 1]) * (self.goal[rows, 0] - 1j * self.goal[rows, 1]))
        width = np.clip(self.reach / np.maximum(np.linalg.norm(goal, axis=-1), 1e-9), 0.02, 0.5)
        angles = prior[:, None] + width[:, None] * self.steps  # (b, n)
        c, s = np.cos(angles)[..., None, None], np.sin(angles)[..., None, None]  # (b, n, 1, 1)
        px, py = predicted[:, None, None, :, 0], predicted[:, None, None, :, 1]  # (b, 1, 1, S_tracks)
        qx, qy = q[:, None, :, None, 0], q[:, None, :, None, 1]  # (b, 1, S_now, 1)
        dr = radius[:, :, None] - self.radius[rows][:, None, :]  # (b, S_now, S_tracks)
        # coordinates apart: a trailing axis of 2 makes the sums several times slower
        d2 = (qx - (c * px - s * py)) ** 2 + (qy - (s * px + c * py)) ** 2 + (dr * dr)[:, None]
        d2 = np.where(alive[:, None, None, :], d2, np.inf)
        cost = np.where(mask[:, None], np.minimum(d2.min(-1), self.gate**2), 0.0).sum(-1)
        best = np.argmin(cost, axis=1)
        d2 = d2[np.arange(b), best]  # (b, S_now, S_tracks)
        # 3: mutual nearest neighbours within the gate
        track = np.argmin(d2, axis=2)  # (b, S_now)
        back = np.argmin(d2, axis=1)  # (b, S_tracks)
        near = np.take_along_axis(d2, track[..., None], axis=2)[..., 0] < self.gate**2
        matched = mask & near & (np.take_along_axis(back, track, axis=1) == np.arange(S))
        # 4: least-squares rotation of the matched pairs about the goal
        p = np.take_along_axis(predicted, track[..., None], axis=1)  # (b, S_now, 2)
        cross = np.where(matched, p[..., 0] * q[..., 1] - p[..., 1] * q[..., 0], 0.0).sum(-1)
        dot = np.where(matched, (p * q).sum(-1), 0.0).sum(-1)
        angle = np.where(matched.any(-1), np.arctan2(cross, dot), angles[np.arange(b), best])
        c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
        # 5: the Kalman update of the matched tracks; new tracks start at rest
        x_hat = _rotate(c, s, p)
        v_hat = _rotate(c, s, np.take_along_axis(self.velocity[rows], track[..., None], axis=1))
        n = np.where(matched, np.take_along_axis(age, track, axis=1), 0)  # measurements before this one
        gain = self.gains[np.minimum(n, len(self.gains) - 1)]  # (b, S, 2); n = 0: [1, 0]
        residual = q - x_hat
        position = np.where(matched[..., None], x_hat + gain[..., :1] * residual, q)
        velocity = np.where(matched[..., None], v_hat + gain[..., 1:] * residual, 0.0)
        velocity = np.where(mask[..., None], velocity, 0.0)
        # 6: the common rotation about the goal (the median rate of the observed tracks) is an error
        rate = (q[..., 0] * velocity[..., 1] - q[..., 1] * velocity[..., 0]) / np.maximum(
            (q * q).sum(-1), 1e-9
        )
        w = _masked_median(rate, mask)[:, None]
        velocity = np.where(
            mask[..., None], velocity - w[..., None] * np.stack([-q[..., 1], q[..., 0]], -1), 0.0
        )
        self.position[rows] = position
        self.velocity[rows] = velocity
        self.radius[rows] = radius
        self.age[rows] = np.where(mask, n + 1, 0)
        self.goal[rows] = goal
        self.started[rows] = True
        return velocity
