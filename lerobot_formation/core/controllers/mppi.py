"""MPPI baseline for the leaders' midpoint unicycle, batched over episodes and samples (numpy only).

Algorithm: information-theoretic Model Predictive Path Integral control (Williams et al. 2017).
Every control step, for each live episode b with nominal control sequence U = (u_0, ..., u_{T-1}):

1. sample K control sequences  u^k_t = clip(mu^k_t + eps^k_t),  eps^k_t ~ N(0, Sigma),
   Sigma = diag(sigma_v^2, sigma_omega^2), where mu^k = U (warm-started nominal) for most samples
   and mu^k = (v_cruise, 0) for a fraction ``cruise_fraction`` of them. Sample 0 is the nominal
   itself (eps = 0) and sample 1 stands still (v = omega = 0), so the plan can always keep or brake;
2. roll every sample out through the midpoint unicycle (``step_midpoint``, explicit Euler, dt 0.1):
   arrays (B, K, 3), one vectorized evaluation per horizon step, a Python loop over time only;
3. score each sample with the path cost S^k (below) plus the information-theoretic control term
   gamma sum_t (u_t - u_ref)^T Sigma^{-1} (u^k_t - u_t), gamma = lambda (1 - alpha), taken around
   the cruise reference u_ref = (v_cruise, 0) instead of 0 (ANCHORS 7: around 0 it drags v to a crawl);
4. weight  w_k = exp(-(S^k - min_j S^j) / lambda) / sum_j exp(-(S^j - min_j S^j) / lambda)  and update

       U <- U + sum_k w_k (u^k - U)  =  sum_k w_k u^k          (Williams et al. 2017, eq. for u*)

   (the update uses the clipped samples, so U stays inside the bounds; with alpha = 1, the
   default, the control term vanishes and smoothness is priced by the explicit cost below);
5. apply u_0, then warm-start: shift U one step left and repeat its last entry.

Path cost of a sample (footprint = the rigid formation template of all N agents, as in PAC's
``footprint_clearance``; c_t = smallest agent-disc clearance of the predicted footprint at step t):

- collision: ``w_collision`` (1000) per step from the first contact on (c_t < the contact margin);
  the flag latches, so colliding later is cheaper than colliding now (ANCHORS 7). The contact margin
  is ``collision_margin`` (0.03 m), lowered to the current footprint clearance when the team is
  already inside it, so the flag never covers every sample just because of the margin;
- proximity: ``w_proximity`` (50) * sum_t max(0, safe_distance - c_t)^2, safe_distance 0.25 m: a
  softer penalty, separate from real contact; it covers the followers' lag behind the template;
- goal: ``w_goal`` (1) * sum_t ctg(p_t) + ``w_terminal`` (10) * ctg(p_T), ctg the grid cost-to-go
  (``navigation.cost_to_go``, obstacles inflated by ``ctg_inflate`` 0.9 m where a cell costs
  ``ctg_wall_cost`` 3 times more, bilinear interpolation): a navigation function has no local
  minima, so obstacle fronts are no dead ends (ANCHORS 7). The field must stay soft: with
  navigation's default walls (x30 within 0.7 m) the valley through a gap is one cell wide, the
  square cannot turn into it, and the team stalls in front of it (seed 1_000_014 timed out);
  after the midpoint first comes within the goal tolerance, a sample costs nothing more (the
  episode would have ended);
- smoothness: ``w_dv`` (1) * sum_t (v_t - v_{t-1})^2 + ``w_domega`` (0.05) * sum_t (omega_t -
  omega_{t-1})^2, with u_{-1} the previously applied action.

Tuning (``benchmarks/mppi_sweep.py``, one factor at a time around K 256, T 30, lambda 1, sigma
(0.2, 0.8) on 40 unseen scenes): every setting but lambda = 10 reached all 40 goals; lambda 0.1 got
there fastest and is the default. The cost-to-go settings were chosen before the sweep, on seeds
1_000_000..1_000_049 and 2_000_000..2_000_099, so the sweep's scenes are not fully unseen by the
design; the defaults also reached all 100 goals of the untouched seeds 1_000_100..1_000_199.

References:
- G. Williams, P. Drews, B. Goldfain, J. M. Rehg, E. A. Theodorou, "Information Theoretic MPC for
  Model-Based Reinforcement Learning", ICRA 2017 (the update and the gamma = lambda (1 - alpha) term).
- G. Williams, A. Aldrich, E. A. Theodorou, "Model Predictive Path Integral Control: From Theory to
  Parallel Computation", J. Guidance, Control, and Dynamics 40(2), 2017.
- pytorch_mppi (UM-ARM-Lab), the batched reference implementation (ANCHORS section 3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lerobot_formation.core.controllers.footprint import template_clearance
from lerobot_formation.core.perception.conditions import Perception
from lerobot_formation.core.world.dynamics import FormationParams, step_midpoint
from lerobot_formation.core.world.navigation import CostToGo, batch_bounds, cost_to_go, refresh_rows


@dataclass(frozen=True)
class MPPIConfig:
    """MPPI hyperparameters. The defaults are the best setting of ``benchmarks/mppi_sweep.py``."""

    num_samples: int = 256  # K
    horizon: int = 30  # T control steps (x dt = 3 s)
    lambda_: float = 0.1  # temperature (sweep: 0.1 reached the goal fastest at 100 % success)
    sigma_v: float = 0.2  # [m/s] exploration noise std of v
    sigma_omega: float = 0.8  # [rad/s] exploration noise std of omega
    alpha: float = 1.0  # IT control-cost weight gamma = lambda (1 - alpha); 1: no control cost term
    noise_smoothing: float = 0.0  # AR(1) coefficient of the noise along the horizon, 0 = white
    v_cruise: float = 0.5  # [m/s] reference speed: initial nominal, cruise samples, control-cost centre
    cruise_fraction: float = 0.1  # share of samples drawn around (v_cruise, 0) instead of the nominal
    w_collision: float = 1000.0  # per step after the first contact (latched)
    collision_margin: float = 0.03  # [m] contact threshold of the predicted footprint
    w_proximity: float = 50.0  # soft penalty weight
    safe_distance: float = 0.25  # [m] footprint clearance below which the proximity penalty starts
    w_goal: float = 1.0  # running cost-to-go weight (per step)
    w_terminal: float = 10.0  # terminal cost-to-go weight
    w_dv: float = 1.0  # smoothness weight on (v_t - v_{t-1})^2
    w_domega: float = 0.05  # smoothness weight on (omega_t - omega_{t-1})^2
    ctg_inflate: float = 0.9  # [m] obstacle inflation of the cost-to-go field (PAC uses 0.9 too)
    ctg_resolution: float = 0.2  # [m] cost-to-go grid cell
    ctg_wall_cost: float = 3.0  # cost-to-go multiplier inside the inflated obstacles
    seed: int = 0

    def __post_init__(self) -> None:
        if self.num_samples < 2 or self.horizon < 1:
            raise ValueError(
                f"need num_samples >= 2 and horizon >= 1, got {self.num_samples}, {self.horizon}"
            )
        if not self.lambda_ > 0:
            raise ValueError(f"lambda_ must be > 0, got {self.lambda_}")
        if self.sigma_v < 0 or self.sigma_omega < 0:
            raise ValueError(f"sigmas must be >= 0, got {self.sigma_v}, {self.sigma_omega}")
        if not 0 <= self.noise_smoothing < 1 or not 0 <= self.cruise_fraction <= 1:
            raise ValueError("noise_smoothing must be in [0, 1) and cruise_fraction in [0, 1]")


def bilinear(ctg: CostToGo, xy: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of the cost-to-go fields ctg.value (B, n, n) at points xy (B, ..., 2) -> (B, ...).

    ``CostToGo.at`` snaps to the nearest 0.2 m cell; MPPI's samples differ by a few cm per step, so
    their costs must vary continuously.
    """
    B, n = ctg.value.shape[0], ctg.value.shape[-1]
    f = np.clip((xy - ctg.origin) / ctg.resolution, 0.0, n - 1.0)
    i0 = np.minimum(f.astype(np.int64), n - 2)  # f >= 0, so truncation is floor
    a = f - i0
    flat = ctg.value.reshape(-1)
    base = (np.arange(B) * n * n).reshape((B,) + (1,) * (xy.ndim - 2))
    k = base + i0[..., 0] * n + i0[..., 1]
    ax, ay = a[..., 0], a[..., 1]
    v00, v01 = flat.take(k), flat.take(k + 1)
    v10, v11 = flat.take(k + n), flat.take(k + n + 1)
    return (v00 * (1 - ax) + v10 * ax) * (1 - ay) + (v01 * (1 - ax) + v11 * ax) * ay


class MPPIController:
    """Batched MPPI behind the ``protocol.Controller`` interface, on what the teams perceive.

    ``reset(view)`` computes the cost-to-go fields from the observed static obstacles
    (``protocol.map_obstacles``), resets the per-episode nominal sequences (indexed by the global
    episode index) and creates the noise generator ``np.random.default_rng(seed)``.
    ``act(view, idx)`` rebuilds the field of an episode whose ``map_version`` changed (a new obstacle
    sensed; with noise, from that step's noisy snapshot), then plans for the live episodes ``idx`` on
    the current observed (noisy) obstacles and pose, and returns (len(idx), 2) actions. Observed moving
    obstacles are predicted at constant velocity along the horizon.
    """

    name = "mppi"

    def __init__(self, config: MPPIConfig | None = None, params: FormationParams | None = None):
        self.config = config or MPPIConfig()
        self.params = params or FormationParams()
        self.template = np.asarray(self.params.graph.template, dtype=np.float64)  # (N, 2) body frame
        self.rng: np.random.Generator | None = None

    def reset(self, view: Perception) -> None:
        from lerobot_formation.core.controllers.protocol import map_obstacles

        c = self.config
        self.goal = np.asarray(view.goal, dtype=np.float64)
        self.ctg_bounds = batch_bounds(self.goal)
        self.ctg = cost_to_go(
            np.asarray(map_obstacles(view), dtype=np.float64),
            self.goal,
            bounds=self.ctg_bounds,
            **self._ctg_options(),
        )
        self.version = np.array(view.map_version, copy=True)
        B = len(view)
        self.nominal = np.zeros((B, c.horizon, 2))
        self.nominal[..., 0] = c.v_cruise
        self.prev_action = np.zeros((B, 2))
        self.rng = np.random.default_rng(c.seed)

    def _ctg_options(self) -> dict:
        c = self.config
        return dict(inflate=c.ctg_inflate, resolution=c.ctg_resolution, wall_cost=c.ctg_wall_cost)

    def refresh_map(self, view: Perception, idx: np.ndarray) -> None:
        """Rebuild the fields of the episodes ``idx`` whose observed obstacle set changed."""
        from lerobot_formation.core.controllers.protocol import map_obstacles

        changed = view.map_version != self.version[idx]
        if changed.any():
            sub = view[changed]
            refresh_rows(
                self.ctg, idx[changed], map_obstacles(sub), sub.goal, self.ctg_bounds, **self._ctg_options()
            )
            self.version[idx[changed]] = sub.map_version

    # -- costs ------------------------------------------------------------------------------------
    def footprint_clearance(self, pose: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
        """Smallest agent-disc clearance of the rigid template at poses (B, K, 3) -> (B, K).

        PAC's footprint (``footprint.template_clearance``), computed in float32 and over the obstacle
        slots that some scene of the batch uses (padded ones are far away with r = 0): MPPI's hot path.
        """
        used = (np.asarray(obstacles)[:, :, 2].astype(np.float32) > 0).any(axis=0)
        return template_clearance(
            pose, obstacles[:, used], self.template, self.params.agent_radius, dtype=np.float32
        )

    def _sample(self, U: np.ndarray) -> np.ndarray:
        """Clipped control samples (B, K, T, 2) around the nominals U (B, T, 2)."""
        c, p = self.config, self.params
        B, T, _ = U.shape
        K = c.num_samples
        eps = self.rng.standard_normal((B, K, T, 2))
        if c.noise_smoothing > 0:
            a = c.noise_smoothing
            for t in range(1, T):
                eps[:, :, t] = a * eps[:, :, t - 1] + np.sqrt(1 - a * a) * eps[:, :, t]
        eps *= np.array([c.sigma_v, c.sigma_omega])
        mean = np.broadcast_to(U[:, None], (B, K, T, 2)).copy()
        n_cruise = int(round(c.cruise_fraction * (K - 2)))
        if n_cruise:
            mean[:, K - n_cruise :, :, 0] = c.v_cruise
            mean[:, K - n_cruise :, :, 1] = 0.0
        u = mean + eps
        u[:, 0] = U  # the nominal itself
        u[:, 1] = 0.0  # stop (no reverse: stopping is the always-available safe action)
        u[..., 0] = np.clip(u[..., 0], 0.0, p.v_max)
        u[..., 1] = np.clip(u[..., 1], -p.omega_max, p.omega_max)
        return u

    def _cost(
        self, pose0: np.ndarray, u: np.ndarray, prev: np.ndarray, obstacles, goal, ctg, obstacle_velocity=None
    ) -> np.ndarray:
        """Path cost (B, K) of the control samples u (B, K, T, 2) from poses (B, 3); obstacles with
        an ``obstacle_velocity`` (B, M, 2) move on at it along the horizon."""
        c, p = self.config, self.params
        B, K, T, _ = u.shape
        pose = np.broadcast_to(pose0[:, None], (B, K, 3))
        clear0 = self.footprint_clearance(pose0[:, None], obstacles)[:, 0]  # (B,)
        margin = np.minimum(c.collision_margin, np.maximum(clear0, 0.0))[:, None]
        crashed = np.zeros((B, K), dtype=bool)
        done = np.zeros((B, K), dtype=bool)  # reached the goal before any contact
        cost = np.zeros((B, K))
        tol2 = p.goal_tolerance**2
        moving = obstacle_velocity is not None and np.any(obstacle_velocity)
        for t in range(T):  # Python loop over time only
            pose = step_midpoint(pose, u[:, :, t], p.dt)
            if moving:
                ahead = obstacles.copy()
                ahead[..., :2] += obstacle_velocity * (p.dt * (t + 1))
                clear = self.footprint_clearance(pose, ahead)
            else:
                clear = self.footprint_clearance(pose, obstacles)
            crashed |= (clear < margin) & ~done
            live = ~done
            cost += c.w_collision * crashed
            cost += np.where(live, c.w_proximity * np.maximum(c.safe_distance - clear, 0.0) ** 2, 0.0)
            g = bilinear(ctg, pose[..., :2])
            cost += np.where(live, c.w_goal * g, 0.0)
            if t == T - 1:
                cost += np.where(live, c.w_terminal * g, 0.0)
            d = pose[..., :2] - goal[:, None]
            done |= (np.sum(d * d, axis=-1) <= tol2) & ~crashed
        du = np.diff(u, axis=2, prepend=np.broadcast_to(prev[:, None, None], (B, K, 1, 2)))
        cost += c.w_dv * np.sum(du[..., 0] ** 2, axis=-1) + c.w_domega * np.sum(du[..., 1] ** 2, axis=-1)
        return cost

    # -- control ----------------------------------------------------------------------------------
    def plan(self, view: Perception, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One MPPI iteration for episodes idx (``view`` their rows): (updated nominals (B, T, 2),
        samples, weights (B, K))."""
        c = self.config
        if self.rng is None:
            raise RuntimeError("call reset(scenes) before act()")
        U = self.nominal[idx]
        u = self._sample(U)
        S = self._cost(
            view.pose,
            u,
            self.prev_action[idx],
            np.asarray(view.obstacles, dtype=np.float64),
            self.goal[idx],
            self.ctg[idx],
            view.obstacle_velocity if view.moving else None,
        )
        if c.alpha < 1:
            sig2 = np.array([c.sigma_v, c.sigma_omega]) ** 2
            ref = np.array([c.v_cruise, 0.0])
            gamma = c.lambda_ * (1 - c.alpha)
            S = S + gamma * np.sum(
                (U[:, None] - ref) / np.maximum(sig2, 1e-12) * (u - U[:, None]), axis=(-1, -2)
            )
        S = S - S.min(axis=1, keepdims=True)
        w = np.exp(-S / c.lambda_)
        w /= w.sum(axis=1, keepdims=True)
        U_new = np.einsum("bk,bktd->btd", w, u)
        # a convex combination of clipped samples, up to rounding: clip away the last ulp
        U_new[..., 0] = np.clip(U_new[..., 0], 0.0, self.params.v_max)
        U_new[..., 1] = np.clip(U_new[..., 1], -self.params.omega_max, self.params.omega_max)
        return U_new, u, w

    def act(self, view: Perception, idx: np.ndarray) -> np.ndarray:
        idx = np.asarray(idx, dtype=np.int64)
        self.refresh_map(view, idx)
        U_new, _, _ = self.plan(view, idx)
        action = U_new[:, 0].copy()
        shifted = np.concatenate([U_new[:, 1:], U_new[:, -1:]], axis=1)
        self.nominal[idx] = shifted
        self.prev_action[idx] = action
        return action
