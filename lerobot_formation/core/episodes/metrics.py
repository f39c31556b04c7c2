"""Per-episode metrics of formation rollouts and their aggregation (SPEC "Metrics").

The paper reports these metrics in the table of its three-way comparison but gives no definitions;
the definitions below are ours (SPEC "Metrics"). Notation for one episode of ``n`` control steps:
midpoint positions ``p_0 .. p_n`` (``poses[..., :2]``), actions ``a_t = [v_t, omega_t]`` for
``t = 0 .. n-1``, control period ``dt``, straight start-goal segment ``S = [s, g]``.

- ``path_length``      L = sum_{t=0}^{n-1} ||p_{t+1} - p_t||
- ``path_optimality``  ||g - s|| / L (NaN if L = 0). The episode ends within the goal tolerance,
  so the value can slightly exceed 1.
- ``tracking_deviation``  mean_{t=0..n} dist(p_t, S), the distance to the SEGMENT (projection
  clamped to its end points).
- ``min_clearance`` / ``mean_clearance``  min / mean over t = 0..n of the midpoint's distance to
  the nearest obstacle surface (``midpoint_clearance``).
- ``formation_min_clearance``  min over t = 0..n of the smallest agent-disc gap to any obstacle
  (``agent_clearance``), the whole formation's minimum.
  The three clearances are NaN (``null`` in results.json, skipped by ``summarize``) in a scene with
  no obstacle: the distance to the nearest of no obstacles is not a number to average (records hold
  +inf there, or the padding distance ``>= geometry.NO_OBSTACLE`` of older records).
- ``mean_control``     mean_{t=0..n-1} ||a_t||
- ``control_smoothness``  mean_{t=1..n-1} ||a_t - a_{t-1}|| / dt (needs n >= 2).
- ``energy``           sum_{t=0..n-1} ||a_t||^2 dt
- ``time``             n dt
- ``mean_velocity``    L / (n dt) (NaN if n = 0).
- ``mean_curvature`` / ``peak_curvature``  mean / max over t = 0..n-1 of
  kappa_t = |omega_t| / max(|v_t|, eps).
- ``jerk``             mean_{t=0..n-3} ||p_{t+3} - 3 p_{t+2} + 3 p_{t+1} - p_t|| / dt^3
  (needs n >= 3, i.e. 4 positions).
- ``orientation_stability``  std_{t=0..n-1} omega_t (population std, heading rate of the actions).
- ``final_formation_error`` / ``mean_formation_error``  e_d at t = n / mean over t = 0..n.
- ``final_follower_velocity_error`` / ``mean_follower_velocity_error``  follower velocity error at
  the last step t = n-1 / mean over t = 0..n-1.
- Outcome flags ``success``, ``collision``, ``timeout`` (bool).
- ``struck_by_mover`` (bool, ``mover_strikes``; the bench adds it): a collision in which a moving
  obstacle closed the gap on a team that was not closing it. At the contact step n, with the
  touching agent i at p_i, the touched obstacle j at c_j, and n_ij = (p_i - c_j) / |p_i - c_j|,
  the agent's own closing speed is -n_ij . (p_i(n) - p_i(n-1)) / dt; the collision counts when
  obstacle j moved over that step and that speed is at most ``MOVER_CLOSING_SPEED``. The leaders
  cannot back up, so a team standing or driving away is struck. The driving benchmarks split
  collisions the same way (nuPlan's "no at-fault collisions": a collision with a stopped ego, or
  from behind, is not the ego's); here it is reported beside the collisions, never instead.

Metrics undefined for an episode (too short, zero length) are NaN. ``summarize`` aggregates
mean +/- std over episodes, the success rate with a Wilson 95 % interval, and counts of
collisions and timeouts.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from lerobot_formation.core.episodes.rollout import COLLISION, SUCCESS, TIMEOUT, EpisodeRecords
from lerobot_formation.core.world.geometry import NO_OBSTACLE

FLAG_KEYS = ("success", "collision", "timeout")
STRUCK_KEY = "struck_by_mover"
MOVER_CLOSING_SPEED = 0.05  # [m/s] an agent closing slower than this on the mover it touched was struck

# Path and motion metrics: aggregated over successful episodes only (SPEC: "path metrics over
# successful episodes"). A collided or timed-out episode's path is cut short or wanders, so its
# length, time, smoothness, ... are not comparable.
SUCCESS_ONLY_KEYS = (
    "path_length",
    "path_optimality",
    "tracking_deviation",
    "min_clearance",
    "mean_clearance",
    "mean_control",
    "control_smoothness",
    "energy",
    "time",
    "mean_velocity",
    "mean_curvature",
    "peak_curvature",
    "jerk",
    "orientation_stability",
    "final_formation_error",
    "mean_formation_error",
    "mean_follower_velocity_error",
    "final_follower_velocity_error",
)
# Aggregated over all episodes: the formation's closest approach to obstacles is a safety measure,
# meaningful (and most informative) on collided and timed-out episodes too.
ALL_EPISODES_KEYS = ("formation_min_clearance",)

METRIC_KEYS = SUCCESS_ONLY_KEYS + ALL_EPISODES_KEYS


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95 % for z = 1.96); (0.0, 1.0) if n = 0.

    The bounds are clamped to [0, 1] and to contain successes / n, which the exact interval does
    (without the clamp, floating point gives 0.9999999999999999 as the upper bound of 100 of 100)."""
    if n < 0 or not 0 <= successes <= n:
        raise ValueError(f"need 0 <= successes <= n, got successes={successes}, n={n}")
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    z2 = z * z
    denom = 1.0 + z2 / n
    centre = (p + z2 / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / denom
    return max(0.0, min(p, centre - half)), min(1.0, max(p, centre + half))


def two_proportion_z(x1: int, n1: int, x2: int, n2: int) -> float:
    """Pooled two-proportion z statistic of success counts x1 of n1 and x2 of n2 episodes (0 when
    both rates are 0 or 1); |z| < 1.96: the two rates are within sampling noise at 5 % (two-sided)."""
    if n1 < 1 or n2 < 1 or not (0 <= x1 <= n1 and 0 <= x2 <= n2):
        raise ValueError(f"need 0 <= x <= n and n >= 1, got x1={x1}, n1={n1}, x2={x2}, n2={n2}")
    p = (x1 + x2) / (n1 + n2)
    se = math.sqrt(p * (1 - p) * (1 / n1 + 1 / n2))
    return 0.0 if se == 0 else (x1 / n1 - x2 / n2) / se


def _masked_sum(x: np.ndarray, m: np.ndarray) -> np.ndarray:
    return np.where(m, x, 0.0).sum(axis=1)


def _masked_mean(x: np.ndarray, m: np.ndarray) -> np.ndarray:
    count = m.sum(axis=1)
    out = np.full(len(x), np.nan)
    ok = count > 0
    out[ok] = _masked_sum(x, m)[ok] / count[ok]
    return out


def _masked_std(x: np.ndarray, m: np.ndarray) -> np.ndarray:
    mean = _masked_mean(x, m)
    dev = np.where(m, x - mean[:, None], 0.0)
    return np.sqrt(_masked_mean(dev * dev, m))


def _masked_extreme(x: np.ndarray, m: np.ndarray, fn) -> np.ndarray:
    fill = np.inf if fn is np.min else -np.inf
    out = fn(np.where(m, x, fill), axis=1) if x.shape[1] else np.full(len(x), fill)
    return np.where(m.any(axis=1), out, np.nan)


def _obstacle_clearance(x: np.ndarray) -> np.ndarray:
    """Clearances with "no obstacle" (+inf or padding ``>= NO_OBSTACLE``) as NaN."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(np.isinf(x) | (x >= NO_OBSTACLE), np.nan, x)


def _take_at(x: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """x[b, idx[b]], NaN where idx[b] < 0."""
    ok = idx >= 0
    out = np.full(len(x), np.nan)
    out[ok] = x[np.flatnonzero(ok), idx[ok]]
    return out


def _segment_distance(p: np.ndarray, s: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Distance from points p (B, K, 2) to the segments [s, g] (B, 2) -> (B, K)."""
    d = g - s  # (B, 2)
    dd = np.einsum("bi,bi->b", d, d)
    rel = p - s[:, None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.einsum("bki,bi->bk", rel, d) / dd[:, None]
    u = np.where(dd[:, None] > 0, np.clip(u, 0.0, 1.0), 0.0)
    return np.linalg.norm(rel - u[..., None] * d[:, None, :], axis=-1)


def episode_metrics(
    records: EpisodeRecords, start: np.ndarray, goal: np.ndarray, eps: float = 1e-3
) -> dict[str, np.ndarray]:
    """Per-episode metrics (see the module docstring): a dict of (B,) float arrays under
    ``METRIC_KEYS`` and (B,) bool arrays under ``FLAG_KEYS``.

    Args:
        records: B padded episodes; entries after each episode's end are ignored (masked by
            ``records.steps``), whatever they hold.
        start: (B, 3) midpoint start pose [x, y, phi] (or (B, 2) positions).
        goal: (B, 2) midpoint goal.
        eps: floor on |v| in the curvature.
    """
    dt = float(records.dt)
    steps = np.asarray(records.steps, dtype=np.int64)
    B, T1 = records.poses.shape[:2]
    T = T1 - 1
    if steps.shape != (B,) or (steps < 0).any() or (steps > T).any():
        raise ValueError(f"steps must be (B,) = ({B},) in [0, {T}], got {steps!r:.120}")
    start = np.asarray(start, dtype=np.float64)[:, :2]
    goal = np.asarray(goal, dtype=np.float64)
    if start.shape != (B, 2) or goal.shape != (B, 2):
        raise ValueError(f"start must be (B, 3) and goal (B, 2) with B={B}, got {start.shape}, {goal.shape}")

    t = np.arange(T1)[None, :]
    pose_ok = t <= steps[:, None]  # (B, T+1): p_0 .. p_n
    act_ok = t[:, :T] < steps[:, None]  # (B, T): a_0 .. a_{n-1}
    p = np.where(pose_ok[..., None], records.poses[..., :2], 0.0)
    a = np.where(act_ok[..., None], records.actions, 0.0)

    out: dict[str, np.ndarray] = {}
    seg = np.linalg.norm(np.diff(p, axis=1), axis=-1)  # (B, T); step t valid iff t < n
    length = _masked_sum(seg, act_ok)
    out["path_length"] = length
    straight = np.linalg.norm(goal - start, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        out["path_optimality"] = np.where(length > 0, straight / length, np.nan)
    out["tracking_deviation"] = _masked_mean(_segment_distance(p, start, goal), pose_ok)

    mid_clear = _obstacle_clearance(records.midpoint_clearance)
    out["min_clearance"] = _masked_extreme(mid_clear, pose_ok, np.min)
    out["mean_clearance"] = _masked_mean(mid_clear, pose_ok)
    out["formation_min_clearance"] = _masked_extreme(
        _obstacle_clearance(records.agent_clearance), pose_ok, np.min
    )

    norm_a = np.linalg.norm(a, axis=-1)
    out["mean_control"] = _masked_mean(norm_a, act_ok)
    da = np.linalg.norm(np.diff(a, axis=1), axis=-1) / dt  # (B, T-1); valid iff t+1 < n
    out["control_smoothness"] = _masked_mean(da, act_ok[:, 1:])
    out["energy"] = _masked_sum(norm_a**2, act_ok) * dt
    time = steps * dt
    out["time"] = time.astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        out["mean_velocity"] = np.where(steps > 0, length / time, np.nan)

    kappa = np.abs(a[..., 1]) / np.maximum(np.abs(a[..., 0]), eps)
    out["mean_curvature"] = _masked_mean(kappa, act_ok)
    out["peak_curvature"] = _masked_extreme(kappa, act_ok, np.max)
    d3 = np.diff(p, n=3, axis=1)  # (B, T-2); valid iff t+3 <= n
    jerk = np.linalg.norm(d3, axis=-1) / dt**3
    out["jerk"] = _masked_mean(jerk, pose_ok[:, 3:])
    out["orientation_stability"] = _masked_std(a[..., 1], act_ok)

    out["final_formation_error"] = _take_at(records.formation_error, steps)
    out["mean_formation_error"] = _masked_mean(records.formation_error, pose_ok)
    out["mean_follower_velocity_error"] = _masked_mean(records.follower_velocity_error, act_ok)
    out["final_follower_velocity_error"] = _take_at(records.follower_velocity_error, steps - 1)

    outcome = np.asarray(records.outcome)
    out["success"] = outcome == SUCCESS
    out["collision"] = outcome == COLLISION
    out["timeout"] = outcome == TIMEOUT
    return out


def mover_strikes(
    records: EpisodeRecords,
    obstacles: np.ndarray,
    mask: np.ndarray,
    agent_radius: float,
    closing_speed: float = MOVER_CLOSING_SPEED,
) -> np.ndarray:
    """(B,) bool: the collisions in which a moving obstacle struck a team that was not closing on it
    (the module docstring's ``struck_by_mover``). ``obstacles`` (B, M, 3): the scenes' obstacles (their
    radii; their centres where ``records.obstacle_paths`` is None: nothing moved), ``mask`` (B, M) the
    real ones. The touching pair is the agent and obstacle of the smallest clearance at the contact."""
    outcome = np.asarray(records.outcome)
    struck = np.zeros(len(outcome), dtype=bool)
    paths = records.obstacle_paths
    if paths is None:
        return struck
    obstacles, mask = np.asarray(obstacles, np.float64), np.asarray(mask, bool)
    B, M = len(outcome), paths.shape[2]
    if obstacles.shape != (B, M, 3) or mask.shape != (B, M):
        raise ValueError(
            f"mover_strikes: need obstacles (B, M, 3) = ({B}, {M}, 3) and mask ({B}, {M}) for records of "
            f"{B} episodes with {M} obstacle paths, got {obstacles.shape} and {mask.shape}"
        )
    for b in np.flatnonzero(outcome == COLLISION):
        n = int(records.steps[b])
        if n < 1:
            continue
        pos, before = records.positions[b, n], records.positions[b, n - 1]  # (N, 2)
        centre, centre_before = paths[b, n], paths[b, n - 1]  # (M, 2)
        gap = np.linalg.norm(pos[:, None] - centre[None], axis=-1) - obstacles[b, :, 2] - agent_radius
        i, j = np.unravel_index(np.argmin(np.where(mask[b][None], gap, np.inf)), gap.shape)
        if not np.any(centre[j] != centre_before[j]):
            continue  # a static obstacle: the team ran into it
        normal = pos[i] - centre[j]
        normal = normal / max(float(np.linalg.norm(normal)), 1e-9)
        agent_closing = -float(normal @ (pos[i] - before[i])) / float(records.dt)
        struck[b] = agent_closing <= closing_speed
    return struck


def _mean_std(x: np.ndarray) -> dict[str, float | None]:
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return {"mean": None, "std": None}
    return {"mean": float(x.mean()), "std": float(x.std())}


def summarize(
    per_episode: dict[str, np.ndarray], successes_only_keys: Iterable[str] = SUCCESS_ONLY_KEYS
) -> dict:
    """Aggregate ``episode_metrics`` output into a JSON-friendly dict of plain Python values.

    Keys: ``n_episodes``, ``success_rate`` (0-1), ``success_ci95`` [lo, hi] (Wilson, z = 1.96),
    ``collisions``, ``timeouts`` (counts), ``collision_rate``, ``timeout_rate``, ``struck_by_mover``
    (the count of those collisions, where ``per_episode`` has the flag), then for every
    continuous metric ``{"mean": float, "std": float}`` (population std over the episodes whose
    value is finite; ``None`` for both if there is none).

    Metrics in ``successes_only_keys`` (default ``SUCCESS_ONLY_KEYS``: path, motion, clearance of
    the midpoint, control and formation metrics) are aggregated over successful episodes only
    (SPEC: "path metrics over successful episodes"); every other continuous metric (by default
    ``ALL_EPISODES_KEYS``: ``formation_min_clearance``) over all episodes. The split is recorded
    under ``"aggregated_over": {"successes": [...], "all": [...]}``. Rates are ``None`` if there
    are no episodes.
    """
    success = np.asarray(per_episode["success"], dtype=bool)
    collision = np.asarray(per_episode["collision"], dtype=bool)
    timeout = np.asarray(per_episode["timeout"], dtype=bool)
    n = len(success)
    n_succ, n_coll, n_time = int(success.sum()), int(collision.sum()), int(timeout.sum())
    lo, hi = wilson_interval(n_succ, n)
    summary: dict = {
        "n_episodes": n,
        "success_rate": n_succ / n if n else None,
        "success_ci95": [lo, hi],
        "collisions": n_coll,
        "timeouts": n_time,
        "collision_rate": n_coll / n if n else None,
        "timeout_rate": n_time / n if n else None,
    }
    if STRUCK_KEY in per_episode:
        summary[STRUCK_KEY] = int(np.asarray(per_episode[STRUCK_KEY], dtype=bool).sum())
    succ_keys = set(successes_only_keys)
    over: dict[str, list[str]] = {"successes": [], "all": []}
    for key, values in per_episode.items():
        if key in FLAG_KEYS or key == STRUCK_KEY:
            continue
        values = np.asarray(values, dtype=np.float64)
        if key in succ_keys:
            summary[key] = _mean_std(values[success])
            over["successes"].append(key)
        else:
            summary[key] = _mean_std(values)
            over["all"].append(key)
    summary["aggregated_over"] = over
    return summary
