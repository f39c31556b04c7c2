import json

import numpy as np
import pytest

from lerobot_formation.core.episodes.metrics import (
    ALL_EPISODES_KEYS,
    FLAG_KEYS,
    METRIC_KEYS,
    episode_metrics,
    summarize,
    two_proportion_z,
    wilson_interval,
)
from lerobot_formation.core.episodes.rollout import COLLISION, SUCCESS, TIMEOUT, EpisodeRecords

DT = 0.1


def make_records(episodes, T=None, dt=DT, pad=np.nan):
    """Build EpisodeRecords from per-episode dicts with 'xy' (n+1, 2) and 'actions' (n, 2);
    optional 'outcome', 'clearance' (n+1,), 'agent_clearance' (n+1,), 'formation_error' (n+1,),
    'follower_velocity_error' (n,). Entries after the end hold ``pad``."""
    B = len(episodes)
    T = T or max(len(e["actions"]) for e in episodes)
    rec = EpisodeRecords(
        poses=np.full((B, T + 1, 3), pad),
        actions=np.full((B, T, 2), pad),
        positions=np.full((B, T + 1, 4, 2), pad),
        formation_error=np.full((B, T + 1), pad),
        follower_velocity_error=np.full((B, T), pad),
        agent_clearance=np.full((B, T + 1), pad),
        midpoint_clearance=np.full((B, T + 1), pad),
        outcome=np.array([e.get("outcome", SUCCESS) for e in episodes]),
        steps=np.array([len(e["actions"]) for e in episodes]),
        dt=dt,
    )
    for b, e in enumerate(episodes):
        n = len(e["actions"])
        rec.poses[b, : n + 1, :2] = e["xy"]
        rec.poses[b, : n + 1, 2] = 0.0
        rec.actions[b, :n] = e["actions"]
        rec.midpoint_clearance[b, : n + 1] = e.get("clearance", np.ones(n + 1))
        rec.agent_clearance[b, : n + 1] = e.get("agent_clearance", np.ones(n + 1))
        rec.formation_error[b, : n + 1] = e.get("formation_error", np.zeros(n + 1))
        rec.follower_velocity_error[b, :n] = e.get("follower_velocity_error", np.zeros(n))
    return rec


def straight(n=10, v=1.0):
    xy = np.stack([np.arange(n + 1) * v * DT, np.zeros(n + 1)], axis=1)
    return {"xy": xy, "actions": np.tile([v, 0.0], (n, 1))}


def metrics_of(episodes, start, goal, **kw):
    rec = make_records(episodes, **kw)
    return episode_metrics(rec, np.atleast_2d(start), np.atleast_2d(goal))


def test_straight_line():
    m = metrics_of([straight(10)], [0.0, 0.0, 0.0], [1.0, 0.0])
    assert m["path_length"][0] == pytest.approx(1.0)
    assert m["path_optimality"][0] == pytest.approx(1.0)
    assert m["tracking_deviation"][0] == pytest.approx(0.0, abs=1e-12)
    assert m["mean_curvature"][0] == 0.0 and m["peak_curvature"][0] == 0.0
    assert m["jerk"][0] == pytest.approx(0.0, abs=1e-6)
    assert m["control_smoothness"][0] == 0.0
    assert m["orientation_stability"][0] == 0.0
    assert m["time"][0] == pytest.approx(1.0)
    assert m["mean_velocity"][0] == pytest.approx(1.0)


def test_circle_arc_curvature():
    v, omega, n = 1.0, 0.5, 20
    R = v / omega
    th = omega * DT * np.arange(n + 1)
    xy = np.stack([R * np.sin(th), R * (1 - np.cos(th))], axis=1)
    ep = {"xy": xy, "actions": np.tile([v, omega], (n, 1))}
    m = metrics_of([ep], [0.0, 0.0, 0.0], xy[-1])
    assert m["mean_curvature"][0] == pytest.approx(omega / v)
    assert m["peak_curvature"][0] == pytest.approx(omega / v)
    assert m["orientation_stability"][0] == pytest.approx(0.0, abs=1e-12)
    assert m["path_optimality"][0] < 1.0


def test_curvature_uses_eps_floor():
    ep = {"xy": np.zeros((3, 2)), "actions": [[0.0, 0.2], [0.0, 0.2]]}
    rec = make_records([ep])
    m = episode_metrics(rec, np.zeros((1, 3)), np.ones((1, 2)), eps=0.01)
    assert m["peak_curvature"][0] == pytest.approx(20.0)
    assert np.isnan(m["path_optimality"][0])  # zero path length


def test_l_shaped_path():
    xy = [[0, 0], [1, 0], [2, 0], [3, 0], [3, 1], [3, 2], [3, 3], [3, 4]]
    ep = {"xy": np.array(xy, float), "actions": np.ones((7, 2))}
    m = metrics_of([ep], [0.0, 0.0, 0.0], [3.0, 4.0])
    assert m["path_length"][0] == pytest.approx(7.0)
    assert m["path_optimality"][0] == pytest.approx(5.0 / 7.0)
    # |x 0.8 - y 0.6| at each point: 0, .8, 1.6, 2.4, 1.8, 1.2, .6, 0
    assert m["tracking_deviation"][0] == pytest.approx(8.4 / 8)


def test_tracking_deviation_parallel_offset_and_segment_end():
    ep = straight(10)
    ep["xy"] = ep["xy"] + [0.0, 0.5]
    m = metrics_of([ep], [0.0, 0.0, 0.0], [1.0, 0.0])
    assert m["tracking_deviation"][0] == pytest.approx(0.5)
    # beyond the goal end of the segment the distance is to the end point, not to the line
    ep = {"xy": np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]), "actions": np.ones((2, 2))}
    m = metrics_of([ep], [0.0, 0.0, 0.0], [1.0, 0.0])
    assert m["tracking_deviation"][0] == pytest.approx(1.0 / 3)


def test_energy_and_control_for_constant_actions():
    ep = {"xy": np.zeros((5, 2)), "actions": np.tile([1.0, 0.5], (4, 1))}
    m = metrics_of([ep], [0.0, 0.0, 0.0], [1.0, 1.0])
    assert m["mean_control"][0] == pytest.approx(np.sqrt(1.25))
    assert m["energy"][0] == pytest.approx(1.25 * 4 * DT)
    assert m["control_smoothness"][0] == 0.0


def test_control_smoothness_and_orientation_stability():
    ep = {"xy": np.zeros((4, 2)), "actions": [[1.0, 1.0], [1.0, 1.0], [2.0, -1.0]]}
    m = metrics_of([ep], [0.0, 0.0, 0.0], [1.0, 1.0])
    assert m["control_smoothness"][0] == pytest.approx((0.0 + np.sqrt(5.0)) / 2 / DT)
    assert m["orientation_stability"][0] == pytest.approx(np.std([1.0, 1.0, -1.0]))


def test_jerk_of_cubic_path():
    # x = t^3 has third derivative 6: the third finite difference / dt^3 is exactly 6
    t = np.arange(8) * DT
    ep = {"xy": np.stack([t**3, np.zeros_like(t)], axis=1), "actions": np.ones((7, 2))}
    m = metrics_of([ep], [0.0, 0.0, 0.0], [1.0, 0.0])
    assert m["jerk"][0] == pytest.approx(6.0)


def test_clearance_and_formation_metrics():
    ep = straight(3)
    ep["clearance"] = [2.0, 1.0, 0.5, 1.5]
    ep["agent_clearance"] = [1.0, 0.2, -0.1, 0.3]
    ep["formation_error"] = [0.0, 0.2, 0.4, 0.6]
    ep["follower_velocity_error"] = [0.3, 0.1, 0.2]
    m = metrics_of([ep], [0.0, 0.0, 0.0], [0.3, 0.0])
    assert m["min_clearance"][0] == 0.5
    assert m["mean_clearance"][0] == pytest.approx(1.25)
    assert m["formation_min_clearance"][0] == pytest.approx(-0.1)
    assert m["final_formation_error"][0] == pytest.approx(0.6)
    assert m["mean_formation_error"][0] == pytest.approx(0.3)
    assert m["final_follower_velocity_error"][0] == pytest.approx(0.2)
    assert m["mean_follower_velocity_error"][0] == pytest.approx(0.2)


@pytest.mark.parametrize("pad", [np.nan, 1e6])
def test_padding_does_not_leak(pad):
    short, long_ = straight(5), straight(12, v=2.0)
    short["actions"][2] = [1.0, 0.3]
    start, goal = np.zeros((2, 3)), np.array([[0.5, 0.0], [2.4, 0.0]])
    batch = episode_metrics(make_records([short, long_], T=15, pad=pad), start, goal)
    for b, ep in enumerate([short, long_]):
        alone = episode_metrics(make_records([ep]), start[b : b + 1], goal[b : b + 1])
        for key in METRIC_KEYS:
            np.testing.assert_allclose(batch[key][b], alone[key][0], err_msg=key)
            assert np.isfinite(batch[key][b]), key


def test_short_episodes_give_nan():
    ep1 = straight(1)
    ep2 = straight(2)
    m = metrics_of([ep1, ep2], np.zeros((2, 3)), [[1.0, 0.0], [1.0, 0.0]], T=5)
    assert np.isnan(m["jerk"]).all()
    assert np.isnan(m["control_smoothness"][0]) and m["control_smoothness"][1] == 0.0
    assert np.isfinite(m["path_length"]).all()


def test_outcome_flags():
    eps = [dict(straight(2), outcome=o) for o in (SUCCESS, COLLISION, TIMEOUT)]
    m = metrics_of(eps, np.zeros((3, 3)), np.ones((3, 2)))
    assert m["success"].tolist() == [True, False, False]
    assert m["collision"].tolist() == [False, True, False]
    assert m["timeout"].tolist() == [False, False, True]
    assert set(m) == set(METRIC_KEYS) | set(FLAG_KEYS)


def test_wilson_interval():
    lo, hi = wilson_interval(62, 100)
    assert lo == pytest.approx(0.522, abs=1e-3) and hi == pytest.approx(0.709, abs=1e-3)
    assert wilson_interval(0, 0) == (0.0, 1.0)
    lo, hi = wilson_interval(10, 10)
    assert hi == pytest.approx(1.0) and lo == pytest.approx(0.7225, abs=1e-3)
    assert wilson_interval(0, 10)[0] == 0.0
    with pytest.raises(ValueError):
        wilson_interval(5, 3)


def test_two_proportion_z():
    # 63/100 vs 67/100 is noise; 50/100 vs 66/100 is not (z = -2.29, by hand)
    assert abs(two_proportion_z(63, 100, 67, 100)) < 1.96
    assert two_proportion_z(50, 100, 66, 100) == pytest.approx(-2.2923, abs=1e-3)
    assert two_proportion_z(66, 100, 50, 100) == pytest.approx(2.2923, abs=1e-3)
    assert two_proportion_z(0, 10, 0, 20) == 0.0 and two_proportion_z(10, 10, 5, 5) == 0.0
    with pytest.raises(ValueError, match="x1=11"):
        two_proportion_z(11, 10, 0, 10)
    with pytest.raises(ValueError, match="n2=0"):
        two_proportion_z(1, 10, 0, 0)


def test_summarize_uses_successes_for_path_metrics():
    eps = [
        dict(straight(4), outcome=SUCCESS, agent_clearance=np.full(5, 0.5)),
        dict(straight(8), outcome=COLLISION, agent_clearance=np.full(9, -0.1)),
        dict(straight(6), outcome=TIMEOUT, agent_clearance=np.full(7, 0.2)),
        dict(straight(2), outcome=SUCCESS, agent_clearance=np.full(3, 0.3)),
    ]
    m = metrics_of(eps, np.zeros((4, 3)), np.tile([1.0, 0.0], (4, 1)))
    s = summarize(m)
    json.dumps(s)
    assert s["n_episodes"] == 4 and s["collisions"] == 1 and s["timeouts"] == 1
    assert s["success_rate"] == 0.5 and s["collision_rate"] == 0.25 and s["timeout_rate"] == 0.25
    assert s["success_ci95"] == pytest.approx(list(wilson_interval(2, 4)))
    assert s["path_length"]["mean"] == pytest.approx(0.3)  # (0.4 + 0.2) / 2, successes only
    assert s["path_length"]["std"] == pytest.approx(0.1)
    assert s["formation_min_clearance"]["mean"] == pytest.approx(0.225)  # all four episodes
    assert set(s["aggregated_over"]["all"]) == set(ALL_EPISODES_KEYS)
    assert all(isinstance(s[k]["mean"], float) for k in METRIC_KEYS)


def test_summarize_without_successes_gives_none():
    eps = [dict(straight(4), outcome=COLLISION), dict(straight(3), outcome=TIMEOUT)]
    s = summarize(metrics_of(eps, np.zeros((2, 3)), np.ones((2, 2))))
    json.dumps(s)
    assert s["success_rate"] == 0.0
    assert s["path_length"] == {"mean": None, "std": None}
    assert s["formation_min_clearance"]["mean"] == pytest.approx(1.0)


def _contact_records(agent_step, obstacle_step, outcome=COLLISION):
    """One two-step episode ending in contact: agent 0 ends at the origin after moving by
    ``agent_step`` over the last step, the one obstacle (radius 0.5) ends touching it after moving by
    ``obstacle_step``; the other agents are far."""
    rec = make_records([dict(straight(2), outcome=outcome)])
    agent_step, obstacle_step = np.asarray(agent_step, float), np.asarray(obstacle_step, float)
    rec.positions[0] = 10.0 + np.arange(4)[None, :, None]  # agents 1-3 far from everything
    rec.positions[0, 2, 0] = 0.0
    rec.positions[0, 1, 0] = -agent_step
    centre = np.array([0.59, 0.0])  # 0.5 + agent radius 0.1 - 1 cm: 1 cm deep
    rec.obstacle_paths = np.full((1, 3, 1, 2), np.nan)
    rec.obstacle_paths[0, 2, 0] = centre
    rec.obstacle_paths[0, 1, 0] = centre - obstacle_step
    rec.obstacle_paths[0, 0, 0] = centre - 2 * obstacle_step
    obstacles = np.array([[[0.59, 0.0, 0.5]]])
    return rec, obstacles, np.ones((1, 1), bool)


@pytest.mark.parametrize(
    "agent_step, obstacle_step, struck",
    [
        ((0.0, 0.0), (-0.03, 0.0), True),  # a standing team, the mover came at it
        ((-0.02, 0.0), (-0.03, 0.0), True),  # the team drove away, the mover was faster
        ((0.004, 0.0), (-0.03, 0.0), True),  # closing at 0.04 m/s: below MOVER_CLOSING_SPEED
        ((0.03, 0.0), (-0.03, 0.0), False),  # the team drove at it too
        ((0.03, 0.0), (0.0, 0.0), False),  # a static obstacle: the team ran into it
        ((0.0, 0.0), (0.0, 0.0), False),  # static, grazed at a standstill: still the team's
    ],
)
def test_mover_strikes_counts_a_moving_obstacle_closing_on_a_team_that_was_not(
    agent_step, obstacle_step, struck
):
    from lerobot_formation.core.episodes.metrics import mover_strikes

    rec, obstacles, mask = _contact_records(agent_step, obstacle_step)
    assert mover_strikes(rec, obstacles, mask, agent_radius=0.1).tolist() == [struck]


def test_mover_strikes_needs_a_collision_and_moving_obstacles_and_summarize_counts_them():
    from lerobot_formation.core.episodes.metrics import STRUCK_KEY, mover_strikes

    rec, obstacles, mask = _contact_records((0.0, 0.0), (-0.03, 0.0), outcome=TIMEOUT)
    assert not mover_strikes(rec, obstacles, mask, 0.1).any()  # no collision: nothing struck
    rec, obstacles, mask = _contact_records((0.0, 0.0), (-0.03, 0.0))
    assert mover_strikes(rec, obstacles, mask, 0.1).all()
    rec.obstacle_paths = None  # a run without moving obstacles records no paths
    assert not mover_strikes(rec, obstacles, mask, 0.1).any()
    rec, obstacles, mask = _contact_records((0.0, 0.0), (-0.03, 0.0))
    with pytest.raises(ValueError, match=r"need obstacles \(B, M, 3\) = \(1, 1, 3\).*got \(1, 2, 3\)"):
        mover_strikes(rec, np.zeros((1, 2, 3)), np.ones((1, 2), bool), 0.1)
    per = episode_metrics(rec, np.zeros((1, 3)), np.ones((1, 2)))
    assert "collisions" in summarize(per) and STRUCK_KEY not in summarize(per)
    per[STRUCK_KEY] = np.array([True])
    s = summarize(per)
    assert s["collisions"] == 1 and s[STRUCK_KEY] == 1
    assert STRUCK_KEY not in s["aggregated_over"]["all"] + s["aggregated_over"]["successes"]
