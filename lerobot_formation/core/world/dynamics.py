"""The one implementation of the team's physics: midpoint unicycle, rigid-bar leaders, followers.

Midpoint unicycle (paper Sec. III, discrete dynamics), action a = [v, omega]:

    x_{t+1}   = x_t + v cos(phi_t) dt
    y_{t+1}   = y_t + v sin(phi_t) dt
    phi_{t+1} = phi_t + omega dt

Leaders: a rigid bar of length 1 centred on the midpoint, perpendicular to the heading:
    p_L1 = p_m - 0.5 (sin phi, -cos phi),   p_L2 = p_m + 0.5 (sin phi, -cos phi).

Followers: unicycles p' = h u, h' = omega x h, driven by the distance-based law of paper eq. (fol1)
with SPEC erratum 1's minus sign:

    chi_i   = sum_{j in N_i} (d_ij^2 - d*_ij^2) (p_i - p_j)
    u_i     = -h_i^T (k1 chi_i + beta sign(chi_i))
    omega_i = -h_i x (k2 chi_i + beta sign(chi_i))

Erratum 2: these gains are stiff; explicit Euler diverges at 10 ms. The followers are integrated
with an inner step ``inner_dt`` (1 ms default) inside each 0.1 s control step, while the leaders
move along the same Euler line/heading ramp as the midpoint within the step.
``sign_epsilon > 0`` replaces sign() by a boundary layer sat(chi / eps), which removes chattering.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from lerobot_formation.core.world.formation_graph import FormationGraph


@dataclass(frozen=True)
class FormationParams:
    """Physics and control parameters (SPEC defaults)."""

    dt: float = 0.1  # [s] control period
    inner_dt: float = 1e-3  # [s] follower sub-step; explicit Euler diverges at 1e-2 (erratum 2)
    k1: float = 35.0
    k2: float = 30.0
    beta: float = 23.0
    sign_epsilon: float = 0.0  # 0: the paper's sign(); > 0: boundary layer sat(chi / eps)
    literal_paper_sign: bool = False  # True: no minus sign (paper eq. fol1 as printed; errors grow)
    v_max: float = 0.6  # [m/s] v is clipped to [0, v_max]
    omega_max: float = 1.5  # [rad/s] omega is clipped to [-omega_max, omega_max]
    agent_radius: float = 0.1  # [m]
    goal_tolerance: float = 0.3  # [m] midpoint distance that counts as reaching the goal
    max_steps: int = 600  # control steps per episode (60 s)
    graph: FormationGraph = field(default_factory=FormationGraph)
    # Follower start in the midpoint body frame (x right, y along heading) and heading relative to
    # the midpoint's. None: the paper's start for the default graph, else the template.
    follower_start: tuple[tuple[float, float], ...] | None = None
    follower_start_heading: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if not 0 < self.inner_dt <= self.dt:
            raise ValueError(f"inner_dt must be in (0, dt={self.dt}], got {self.inner_dt}")
        n_sub = self.dt / self.inner_dt
        if abs(n_sub - round(n_sub)) > 1e-6:
            raise ValueError(f"dt / inner_dt must be an integer, got {self.dt} / {self.inner_dt} = {n_sub}")
        for name in ("k1", "k2", "beta", "v_max", "omega_max", "agent_radius", "goal_tolerance"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"{name} must be finite and non-negative, got {v}")
        if self.sign_epsilon < 0:
            raise ValueError(f"sign_epsilon must be >= 0, got {self.sign_epsilon}")

    @property
    def n_substeps(self) -> int:
        return round(self.dt / self.inner_dt)

    def follower_start_body(self) -> tuple[np.ndarray, np.ndarray]:
        """Follower start offsets (F, 2) in the body frame and headings (F,) relative to the midpoint."""
        F = self.graph.n_followers
        if self.follower_start is not None:
            pos = np.asarray(self.follower_start, dtype=np.float64)
            head = np.asarray(self.follower_start_heading or (0.0,) * F, dtype=np.float64)
        elif self.graph == FormationGraph():
            # Paper: F1 (-0.2, -0.9) heading 180 deg, F2 (0.4, -1.0) heading 90 deg, midpoint heading 90 deg.
            pos = np.array([[-0.2, -0.9], [0.4, -1.0]])
            head = np.array([np.pi / 2, 0.0])
        else:
            pos = np.asarray(self.graph.template, dtype=np.float64)[2:]
            head = np.zeros(F)
        if pos.shape != (F, 2) or head.shape != (F,):
            raise ValueError(f"follower start must be ({F}, 2) and ({F},), got {pos.shape} and {head.shape}")
        return pos, head


@dataclass
class FormationState:
    """State of B teams.

    Attributes:
        pose: (B, 3) midpoint [x, y, phi].
        velocity: (B, 3) midpoint [x', y', omega] over the last control step.
        follower_pos: (B, F, 2) [m].
        follower_theta: (B, F) follower heading angles [rad].
        follower_vel: (B, F, 2) follower velocity averaged over the last control step [m/s].
    """

    pose: np.ndarray
    velocity: np.ndarray
    follower_pos: np.ndarray
    follower_theta: np.ndarray
    follower_vel: np.ndarray

    def copy(self) -> FormationState:
        return FormationState(*(np.array(a, copy=True) for a in self.arrays()))

    def arrays(self) -> tuple[np.ndarray, ...]:
        return (self.pose, self.velocity, self.follower_pos, self.follower_theta, self.follower_vel)

    def __getitem__(self, idx) -> FormationState:
        return FormationState(*(np.array(a[idx], copy=True) for a in self.arrays()))

    def set(self, mask: np.ndarray, other: FormationState) -> None:
        """Overwrite the teams where mask (B,) is True with ``other`` (rows in the same order)."""
        for a, b in zip(self.arrays(), other.arrays(), strict=True):
            a[mask] = b


def rotate_body(offsets: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Body-frame offsets (..., 2) (x right, y along heading) to world frame; phi has shape (...).

    The rotation by a = phi - pi/2: [x, y] = [bx cos a - by sin a, bx sin a + by cos a]. The team's
    start (``initial_state``), the template slots (``desired_follower_positions``) and the scenes'
    start check use it. ``body_to_world`` is the same rotation for the footprint hot paths; the two
    round differently in the last bit (cos(phi - pi/2) is not sin(phi) in floating point), and the
    recorded results depend on those bits, so both stay.
    """
    a = phi - np.pi / 2
    c, s = np.cos(a), np.sin(a)
    x = offsets[..., 0] * c - offsets[..., 1] * s
    y = offsets[..., 0] * s + offsets[..., 1] * c
    return np.stack([x, y], axis=-1)


def body_to_world(bx, by, x, y, phi, dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
    """Body-frame points (bx, by) of teams at midpoint poses (x, y, phi) in the world, coordinates apart:

        X = x + bx sin(phi) + by cos(phi),   Y = y - bx cos(phi) + by sin(phi)

    (``rotate_body``'s rotation plus the translation). All arguments broadcast, e.g. template
    columns (N, 1, 1) against poses (B, K) give agents (N, B, K). The footprint checks of PAC, MPPI
    and candidate scoring use it; ``dtype=np.float32`` is MPPI's fast path (the trigonometry in
    float64, then everything cast).
    """
    s = np.sin(phi).astype(dtype, copy=False)
    c = np.cos(phi).astype(dtype, copy=False)
    x, y, bx, by = (np.asarray(v).astype(dtype, copy=False) for v in (x, y, bx, by))
    return x + bx * s + by * c, y - bx * c + by * s


def leader_positions(pose: np.ndarray) -> np.ndarray:
    """Rigid-bar leaders, (..., 3) midpoint poses -> (..., 2, 2): p_L1 = p_m - 0.5 (sin, -cos)."""
    s, c = np.sin(pose[..., 2]), np.cos(pose[..., 2])
    half = 0.5 * np.stack([s, -c], axis=-1)
    p = pose[..., :2]
    return np.stack([p - half, p + half], axis=-2)


def initial_state(start: np.ndarray, params: FormationParams | None = None) -> FormationState:
    """Teams at rest at the start poses (B, 3)."""
    params = params or FormationParams()
    start = np.asarray(start, dtype=np.float64)
    B = len(start)
    offs, head = params.follower_start_body()
    fpos = rotate_body(np.broadcast_to(offs, (B, *offs.shape)), start[:, 2][:, None].repeat(len(offs), 1))
    fpos = fpos + start[:, None, :2]
    return FormationState(
        pose=start.copy(),
        velocity=np.zeros((B, 3)),
        follower_pos=fpos,
        follower_theta=start[:, 2][:, None] + head[None, :],
        follower_vel=np.zeros((B, len(offs), 2)),
    )


def agent_positions(state: FormationState) -> np.ndarray:
    """All agents, leaders first: (B, N, 2)."""
    return np.concatenate([leader_positions(state.pose), state.follower_pos], axis=1)


def formation_error(positions: np.ndarray, graph: FormationGraph | None = None) -> np.ndarray:
    """e_d = ||d - d*|| over the edges, positions (..., N, 2) -> (...)."""
    graph = graph or FormationGraph()
    z = positions[..., graph.edge_i, :] - positions[..., graph.edge_j, :]
    d = np.sqrt(np.sum(z * z, axis=-1))
    return np.sqrt(np.sum((d - np.asarray(graph.distances)) ** 2, axis=-1))


def check_action(action, batch_size: int) -> np.ndarray:
    """Validate a batch of actions: (B, 2) finite floats; errors name the value."""
    a = np.asarray(action)
    if a.dtype.kind not in "fiu":
        raise ValueError(f"action must be a float array of shape ({batch_size}, 2), got dtype {a.dtype}")
    if a.shape != (batch_size, 2):
        raise ValueError(f"action must have shape ({batch_size}, 2) [v, omega], got {a.shape}")
    if not np.all(np.isfinite(a)):
        bad = a[~np.isfinite(a).all(axis=1)][0]
        raise ValueError(f"action must be finite, got {bad.tolist()}")
    return a.astype(np.float64)


def clip_action(action: np.ndarray, params: FormationParams) -> np.ndarray:
    """Clip [v, omega] to v in [0, v_max], |omega| <= omega_max."""
    return np.stack(
        [
            np.clip(action[..., 0], 0.0, params.v_max),
            np.clip(action[..., 1], -params.omega_max, params.omega_max),
        ],
        axis=-1,
    )


def rate_limit(
    previous: np.ndarray,
    command: np.ndarray,
    max_linear_accel: float | None,
    max_angular_accel: float | None,
    dt: float,
) -> np.ndarray:
    """The second-order unicycle's executed velocity (B, 2): the previous executed [v, omega] (B, 2)
    moves toward the ``command`` (B, 2) by at most the acceleration times dt per control step,

        v_k = v_{k-1} + clip(v_cmd - v_{k-1}, -a_v dt, a_v dt),
        omega_k = omega_{k-1} + clip(omega_cmd - omega_{k-1}, -a_omega dt, a_omega dt),

    a_v = ``max_linear_accel`` [m/s^2], a_omega = ``max_angular_accel`` [rad/s^2] (None: that
    component follows the command at once). ``core.perception.conditions.ConditionedWorld.execute`` applies it
    to the clipped command before ``step``, which then moves the team with the result."""
    out = np.array(command, dtype=np.float64)
    for k, accel in enumerate((max_linear_accel, max_angular_accel)):
        if accel is not None:
            dv = accel * dt
            # np.minimum/np.maximum: np.clip's numbers at half its call overhead (a hot path of best-of-K)
            out[:, k] = previous[:, k] + np.minimum(np.maximum(out[:, k] - previous[:, k], -dv), dv)
    return out


def rate_limit_sequence(
    previous: np.ndarray,
    commands: np.ndarray,
    max_linear_accel: float | None,
    max_angular_accel: float | None,
    dt: float,
) -> np.ndarray:
    """``rate_limit`` along command sequences: the executed velocities (B, C, T, 2) of commands
    (B, C, T, 2) from the executed [v, omega] (B, 2) before the first; step k starts from step
    k - 1's result. The commands are returned as they are when neither limit is set."""
    if max_linear_accel is None and max_angular_accel is None:
        return commands
    B, C, T, _ = commands.shape
    out = np.empty((B, C, T, 2))
    now = np.repeat(np.asarray(previous, dtype=np.float64), C, axis=0)  # (B * C, 2)
    flat = commands.reshape(B * C, T, 2)
    for k in range(T):
        now = rate_limit(now, flat[:, k], max_linear_accel, max_angular_accel, dt)
        out[:, :, k] = now.reshape(B, C, 2)
    return out


def step_midpoint(pose: np.ndarray, action: np.ndarray, dt) -> np.ndarray:
    """Midpoint unicycle, explicit Euler (paper's discrete dynamics). (..., 3), (..., 2) -> (..., 3).

    ``dt`` [s] may be an array broadcasting against (...): ``step`` evaluates all its sub-step ends at
    once, MPPI steps its samples with the control period.
    """
    v, w = action[..., 0], action[..., 1]
    phi = pose[..., 2]
    return np.stack(
        [pose[..., 0] + v * np.cos(phi) * dt, pose[..., 1] + v * np.sin(phi) * dt, phi + w * dt], axis=-1
    )


def midpoint_velocity(pose: np.ndarray, action: np.ndarray) -> np.ndarray:
    """Midpoint velocity [x', y', omega] (..., 3) over a step from ``pose`` (..., 3) with the (clipped)
    ``action`` (..., 2): the unicycle's [v cos phi, v sin phi, omega] at the step's start heading."""
    v, w, phi = action[..., 0], action[..., 1], pose[..., 2]
    return np.stack([v * np.cos(phi), v * np.sin(phi), w], axis=-1)


def rollout_poses(pose: np.ndarray, actions: np.ndarray, dt: float) -> np.ndarray:
    """Midpoint poses after each action of candidate sequences, pose (B, 3), actions (B, C, T, 2) ->
    (B, C, T, 3): ``step_midpoint`` repeated T times, written as cumulative sums (one array operation
    per coordinate instead of a loop over T; the sums round differently from the loop)."""
    B, C, T, _ = actions.shape
    v, w = actions[..., 0], actions[..., 1]
    phi = pose[:, 2][:, None, None] + np.cumsum(w, axis=-1) * dt  # heading after step k
    phi_before = np.concatenate(
        [np.broadcast_to(pose[:, 2][:, None, None], (B, C, 1)), phi[..., :-1]], axis=-1
    )
    x = pose[:, 0][:, None, None] + np.cumsum(v * np.cos(phi_before), axis=-1) * dt
    y = pose[:, 1][:, None, None] + np.cumsum(v * np.sin(phi_before), axis=-1) * dt
    return np.stack([x, y, phi], axis=-1)


def constant_action_poses(pose: np.ndarray, action: np.ndarray, dt: float, horizon: int) -> np.ndarray:
    """Midpoint poses after each of ``horizon`` steps holding one action, pose (B, 3), action (B, C, 2)
    -> (B, C, T, 3): ``rollout_poses`` of a constant sequence, in closed form (phi_k = phi_0 + k omega
    dt; PAC's footprint governor; it rounds differently from the cumulative sums)."""
    B, C, _ = action.shape
    v, w = action[..., 0], action[..., 1]
    k = np.arange(1, horizon + 1)[None, None, :]
    phi0 = pose[:, 2][:, None, None]
    phi = phi0 + w[..., None] * dt * k  # (B, C, T): heading after k steps
    # Euler positions: x_k = x_0 + v dt sum_{j<k} cos(phi_j)
    phis = np.concatenate([np.broadcast_to(phi0, (B, C, 1)), phi[..., :-1]], axis=-1)
    x = pose[:, 0][:, None, None] + v[..., None] * dt * np.cumsum(np.cos(phis), axis=-1)
    y = pose[:, 1][:, None, None] + v[..., None] * dt * np.cumsum(np.sin(phis), axis=-1)
    return np.stack([x, y, phi], axis=-1)


class _FollowerLaw:
    """Precomputed edge bookkeeping for the follower law; ``__call__`` is the hot path.

    Works on x and y coordinates apart and sums chi_i edge by edge (no BLAS, no reductions), so a
    team's result does not depend on the batch it is in: batched and per-scene stepping agree bit
    for bit, which matters because sign() amplifies the last bit.
    """

    def __init__(self, params: FormationParams):
        g = params.graph
        self.ei, self.ej = g.edge_i, g.edge_j
        self.d2 = g.desired_sq
        H = g.incidence[2:]  # (F, E): +1 first end, -1 second end
        self.terms = [[(e, float(H[f, e])) for e in range(H.shape[1]) if H[f, e] != 0] for f in range(len(H))]
        self.k1, self.k2, self.beta = params.k1, params.k2, params.beta
        self.eps = params.sign_epsilon
        self.sgn = 1.0 if params.literal_paper_sign else -1.0

    def chi(self, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """chi_i = sum_j (d_ij^2 - d*^2)(p_i - p_j) for the followers; px, py (B, N) -> (B, F) each."""
        zx = px[:, self.ei] - px[:, self.ej]  # (B, E)
        zy = py[:, self.ei] - py[:, self.ej]
        err = zx * zx + zy * zy - self.d2
        wx, wy = err * zx, err * zy
        B, F = len(px), len(self.terms)
        cx, cy = np.zeros((B, F)), np.zeros((B, F))
        for f, terms in enumerate(self.terms):
            for e, sgn in terms:
                if sgn > 0:
                    cx[:, f] += wx[:, e]
                    cy[:, f] += wy[:, e]
                else:
                    cx[:, f] -= wx[:, e]
                    cy[:, f] -= wy[:, e]
        return cx, cy

    def __call__(self, px, py, hx, hy) -> tuple[np.ndarray, np.ndarray]:
        """Agents px, py (B, N), follower headings hx, hy (B, F) -> u, omega (B, F)."""
        cx, cy = self.chi(px, py)
        if self.eps > 0:
            sx, sy = np.clip(cx / self.eps, -1.0, 1.0), np.clip(cy / self.eps, -1.0, 1.0)
        else:
            sx, sy = np.sign(cx), np.sign(cy)
        u = self.sgn * (
            hx * (self.k1 * cx + self.beta * sx) + hy * (self.k1 * cy + self.beta * sy)
        )  # -h^T g1
        om = self.sgn * (
            hx * (self.k2 * cy + self.beta * sy) - hy * (self.k2 * cx + self.beta * sx)
        )  # -h x g2
        return u, om


def follower_law(p: np.ndarray, theta: np.ndarray, params: FormationParams) -> tuple[np.ndarray, np.ndarray]:
    """Follower law (paper eq. fol1 with erratum 1's minus sign). p (B, N, 2), theta (B, F) ->
    u (B, F) [m/s], omega (B, F) [rad/s]."""
    return _law(params)(p[..., 0], p[..., 1], np.cos(theta), np.sin(theta))


@functools.lru_cache(maxsize=64)
def _law(params: FormationParams) -> _FollowerLaw:
    return _FollowerLaw(params)


def step(state: FormationState, action: np.ndarray, params: FormationParams | None = None) -> FormationState:
    """Advance B teams by one control step. ``action`` (B, 2) is clipped to the bounds first.

    The leaders follow the midpoint's Euler step linearly in time within the step; the followers
    are integrated with ``params.n_substeps`` explicit Euler sub-steps of the follower law.
    Returns a new state; the input is not modified.
    """
    params = params or FormationParams()
    a = clip_action(action, params)
    B = len(a)
    n = params.n_substeps
    h = params.inner_dt
    pose0 = state.pose
    # Leader poses at every sub-step end tau_k = k h, k = 1..n: (n, B, 3).
    tau = (h * np.arange(1, n + 1))[:, None]
    poses = step_midpoint(pose0, a, tau)
    leaders = leader_positions(poses)  # (n, B, 2, 2)
    # The law at sub-step k uses the leader positions at its start: tau_{k-1}.
    leaders_start = np.concatenate([leader_positions(pose0)[None], leaders[:-1]], axis=0)
    law = _law(params)
    fx = state.follower_pos[..., 0].copy()
    fy = state.follower_pos[..., 1].copy()
    th = state.follower_theta.copy()
    lx, ly = leaders_start[..., 0], leaders_start[..., 1]  # (n, B, 2)
    px = np.empty((B, params.graph.n_agents))
    py = np.empty((B, params.graph.n_agents))
    with np.errstate(over="ignore", invalid="ignore"):  # divergence is reported below
        for k in range(n):  # loop over time only
            px[:, :2], py[:, :2] = lx[k], ly[k]
            px[:, 2:], py[:, 2:] = fx, fy
            hx, hy = np.cos(th), np.sin(th)
            u, om = law(px, py, hx, hy)
            hu = h * u
            fx += hu * hx
            fy += hu * hy
            th += h * om
    fp = np.stack([fx, fy], axis=-1)
    if not (np.isfinite(fp).all() and np.isfinite(th).all()):
        bad = np.flatnonzero(~np.isfinite(fp).all(axis=(1, 2)) | ~np.isfinite(th).all(axis=1))
        raise FloatingPointError(
            f"follower state diverged to non-finite values in teams {bad[:5].tolist()} "
            f"(inner_dt={params.inner_dt}, literal_paper_sign={params.literal_paper_sign}); "
            "explicit Euler needs inner_dt <= 1e-3 with the paper's gains (erratum 2)"
        )
    return FormationState(
        pose=poses[-1],
        velocity=midpoint_velocity(pose0, a),
        follower_pos=fp,
        follower_theta=th,
        follower_vel=(fp - state.follower_pos) / params.dt,
    )


def desired_follower_positions(pose: np.ndarray, graph: FormationGraph | None = None) -> np.ndarray:
    """Where the followers should be for a midpoint pose (..., 3): (..., F, 2) from the template."""
    graph = graph or FormationGraph()
    tmpl = np.asarray(graph.template)[2:]
    offs = np.broadcast_to(tmpl, (*pose.shape[:-1], *tmpl.shape))
    phi = np.broadcast_to(pose[..., 2][..., None], offs.shape[:-1])
    return rotate_body(offs, phi) + pose[..., None, :2]
