"""The safety layer: the CBF filter never makes a safe action unsafe and stops collisions; best-of-K
never keeps a colliding chunk when a safe one exists."""

import numpy as np
import pytest

from lerobot_formation.core import dynamics
from lerobot_formation.core.dynamics import FormationParams
from lerobot_formation.core.geometry import agent_clearances
from lerobot_formation.core.obstacle_grid import environment_state
from lerobot_formation.core.safety import (
    barrier_rows,
    cbf_filter,
    cost_to_go_progress,
    decode_nearest,
    select_chunk,
)
from lerobot_formation.core.scene import FAR

P = FormationParams()
TEMPLATE = np.asarray(P.graph.template)
LOW, HIGH = np.array([0.0, -P.omega_max]), np.array([P.v_max, P.omega_max])


def _filter(a, obs, margin=0.1, rate=2.0):
    return cbf_filter(a, obs, TEMPLATE, P.agent_radius, margin, rate, LOW, HIGH)


def test_filter_leaves_actions_that_satisfy_every_barrier_unchanged():
    rng = np.random.default_rng(0)
    obs = rng.uniform(-4, 4, (300, 6, 3))
    obs[..., 2] = rng.uniform(0.2, 0.8, (300, 6))
    a = np.stack([rng.uniform(0, 0.6, 300), rng.uniform(-1.5, 1.5, 300)], -1)
    A, b, h = barrier_rows(obs, TEMPLATE, P.agent_radius, 0.1, 2.0)
    ok = ((np.einsum("brd,bd->br", A, a) >= b).all(axis=1)) & (h >= 0).all(axis=1)
    out, changed = _filter(a, obs)
    assert ok.sum() > 50
    np.testing.assert_array_equal(out[ok], a[ok])
    assert not changed[ok].any()
    # and what it returns satisfies the barrier rows wherever the team is outside the margin
    A2, b2, _ = barrier_rows(obs, TEMPLATE, P.agent_radius, 0.1, 2.0)
    safe_now = (h >= 0).all(axis=1)
    assert (np.einsum("brd,bd->br", A2, out)[safe_now] >= b2[safe_now] - 1e-6).all()
    assert ((out >= LOW - 1e-12) & (out <= HIGH + 1e-12)).all()


def test_filter_stops_a_team_driving_into_an_obstacle():
    """Full speed at an obstacle in front of a leader: unfiltered it collides, filtered it never does
    (followers simulated with the real follower law, not assumed on their slots)."""
    goal = np.array([[0.0, 20.0]])
    obstacles = np.array([[[0.5, 2.0, 0.4], [-1.6, 3.5, 0.5], [FAR, FAR, 0.0]]])
    mask = np.array([[True, True, False]])
    for use_filter, expect_hit in ((False, True), (True, False)):
        state = dynamics.initial_state(np.array([[0.0, 0.0, np.pi / 2]]), P)
        hit = False
        for _ in range(80):
            a = np.array([[0.6, 0.0]])
            if use_filter:
                env = environment_state(obstacles, mask, goal, "nearest", pose=state.pose)
                _, obs_b, _ = decode_nearest(env, 12)
                a, _ = _filter(a, obs_b)
            state = dynamics.step(state, a, P)
            clear = agent_clearances(dynamics.agent_positions(state), obstacles, P.agent_radius)
            hit |= bool((clear < 0).any())
        assert hit == expect_hit


def test_select_chunk_prefers_safe_then_progress():
    obstacles = np.array([[[0.5, 1.2, 0.3]]])  # in front of L2
    goal = np.array([[0.0, 6.0]])
    T = 16
    straight = np.tile([0.6, 0.0], (T, 1))  # L2 runs into the obstacle
    turn = np.tile([0.4, -0.6], (T, 1))  # turns away from it: safe
    slow = np.tile([0.05, 0.0], (T, 1))  # safe, little progress
    cand = np.stack([straight, slow, turn])[None]
    chosen, info = select_chunk(cand, obstacles, goal, TEMPLATE, P.dt, P.agent_radius, 0.1)
    assert not info["safe"][0, 0] and info["safe"][0, 1] and info["safe"][0, 2]
    np.testing.assert_array_equal(chosen[0], cand[0, info["choice"][0]])
    assert info["choice"][0] in (1, 2) and not info["escaped"][0]  # never the colliding one
    # K = 1 and safe: that candidate
    _, info1 = select_chunk(cand[:, 1:2], obstacles, goal, TEMPLATE, P.dt, P.agent_radius, 0.1)
    assert info1["choice"][0] == 0
    # none safe: a safe escape manoeuvre if there is one, else the largest clearance
    blocked = np.array([[[0.5, 0.5, 0.3], [-0.5, 0.5, 0.3]]])
    _, info2 = select_chunk(cand, blocked, goal, TEMPLATE, P.dt, P.agent_radius, 0.1)
    assert not info2["any_safe"][0]
    if not info2["escaped"][0]:
        assert info2["choice"][0] == np.argmax(info2["clearance"][0])
    _, info3 = select_chunk(cand, blocked, goal, TEMPLATE, P.dt, P.agent_radius, 0.1, escape=False)
    assert info3["choice"][0] == np.argmax(info3["clearance"][0])


def test_progress_goes_round_an_obstacle_not_through_it():
    """Cost-to-go progress prefers the chunk that starts round an obstacle on the straight line over
    the one that heads at it (straight-line progress would pick the latter)."""
    obstacles = np.array([[[0.0, 3.2, 0.8]]])
    goal = np.array([[0.0, 7.0]])
    T = 16
    straight = np.tile([0.5, 0.0], (T, 1))
    veer = np.tile([0.5, 0.35], (T, 1))
    cand = np.stack([straight, veer])[None]
    _, eu = select_chunk(cand, obstacles, goal, TEMPLATE, P.dt, P.agent_radius, 0.1, "euclidean")
    _, ctg = select_chunk(cand, obstacles, goal, TEMPLATE, P.dt, P.agent_radius, 0.1)
    assert eu["safe"][0].all()
    assert eu["choice"][0] == 0 and ctg["choice"][0] == 1


def test_escape_advantage_goes_round_a_team_pressed_against_an_obstacle():
    """Every sampled chunk barely moves (the policy presses the team against a wall ahead): they are
    safe, so by default one of them is kept and the team stalls; with an escape advantage the safe
    manoeuvre with the most cost-to-go progress wins. With a sampled chunk that makes real progress,
    the sampled chunk still wins."""
    obstacles = np.array([[[0.0, 1.6, 0.5]]])  # straight ahead of the bar
    goal = np.array([[0.0, 6.0]])
    T = 16
    creep = np.stack([np.tile([0.02, 0.0], (T, 1)), np.tile([0.0, 0.05], (T, 1))])[None]
    _, plain = select_chunk(creep, obstacles, goal, TEMPLATE, P.dt, P.agent_radius, 0.1)
    assert plain["any_safe"][0] and not plain["escaped"][0]
    kept, adv = select_chunk(
        creep, obstacles, goal, TEMPLATE, P.dt, P.agent_radius, 0.1, escape_advantage=0.1
    )
    assert adv["escaped"][0]
    assert abs(kept[0, 0, 1]) > 0  # an arc or a turn, not the blocked straight line
    # a sampled chunk that makes real progress (the obstacle off to the side) still wins
    aside = np.array([[[2.5, 2.0, 0.5]]])
    drive = np.concatenate([creep, np.tile([0.5, 0.0], (T, 1))[None, None]], axis=1)
    _, adv2 = select_chunk(drive, aside, goal, TEMPLATE, P.dt, P.agent_radius, 0.1, escape_advantage=0.1)
    assert adv2["safe"][0, 2] and adv2["progress"][0, 2] > 0.6
    assert adv2["choice"][0] == 2 and not adv2["escaped"][0]


def test_progress_of_an_episode_does_not_depend_on_the_rest_of_its_batch():
    """The scorer's grid is fixed in the body frame: a batch (the engine, lerobot-eval's vector env)
    scores each episode exactly as ``select_action`` at B = 1 does, goals near and far."""
    rng = np.random.default_rng(5)
    B, K = 6, 9
    obstacles = np.concatenate([rng.uniform(-5, 5, (B, 12, 2)), rng.uniform(0.2, 1.0, (B, 12, 1))], -1)
    goal = np.array([[0.5, 1.0], [3.0, 5.0], [-9.0, 2.0], [0.0, -7.5], [6.0, 6.0], [-2.0, -20.0]])
    end = rng.uniform(-1, 1, (B, K, 2))
    batch = cost_to_go_progress(obstacles, goal, end, 6.0)
    for b in range(B):
        alone = cost_to_go_progress(obstacles[b : b + 1], goal[b : b + 1], end[b : b + 1], 6.0)
        assert np.array_equal(alone[0], batch[b])
    assert np.isfinite(batch).all()


def test_blocked_fallback_stop_turns_a_predicted_contact_into_a_stop():
    """Nothing safe (every sampled chunk and manoeuvre drives an agent into an obstacle hemming it in):
    "widest" keeps the widest sampled chunk, which still hits; "stop" holds the team still (zero
    actions, which keep its clearance). Nothing safe but no contact predicted: "stop" moves on."""
    T = 16
    # every agent hemmed in by four small obstacles 3 mm away: any motion of a few cm touches one
    gap = 0.003
    r = 0.05
    d = P.agent_radius + r + gap
    ring = [(x + dx, y + dy, r) for x, y in TEMPLATE for dx, dy in ((d, 0), (-d, 0), (0, d), (0, -d))]
    obstacles = np.array([ring])
    goal = np.array([[0.0, 6.0]])
    rng = np.random.default_rng(1)
    cand = np.stack([rng.uniform(0.1, 0.6, (1, 10, T)), rng.uniform(-1.5, 1.5, (1, 10, T))], axis=-1)
    args = (cand, obstacles, goal, TEMPLATE, P.dt, P.agent_radius, 0.1)
    widest, info_w = select_chunk(*args, escape_advantage=0.1)
    assert not info_w["any_safe"][0] and not info_w["stopped"][0]
    assert info_w["clearance"][0].max() < 0  # what "widest" keeps collides
    np.testing.assert_array_equal(widest[0], cand[0, np.argmax(info_w["clearance"][0])])
    stop, info_s = select_chunk(*args, escape_advantage=0.1, blocked_fallback="stop")
    assert info_s["stopped"][0] and not info_s["escaped"][0]
    np.testing.assert_array_equal(stop[0], np.zeros((T, 2)))
    # nothing safe, but no contact: an obstacle 0.3 m ahead of both leaders, every candidate drives
    # 0.25 m toward it (ends inside the 0.1 m margin, not in contact); without escapes it is kept
    lead_y = TEMPLATE[:, 1].max()
    ahead = np.array([[[x, lead_y + P.agent_radius + 0.3 + 0.4, 0.4] for x in (-0.6, 0.0, 0.6)]])
    slow = np.tile([0.25 / (T * P.dt), 0.0], (1, 3, T, 1))
    kept, info_k = select_chunk(
        slow, ahead, goal, TEMPLATE, P.dt, P.agent_radius, 0.1, escape=False, blocked_fallback="stop"
    )
    assert not info_k["any_safe"][0] and not info_k["stopped"][0]
    assert 0 <= info_k["clearance"][0].max() < 0.1
    np.testing.assert_array_equal(kept[0], slow[0, 0])
    with pytest.raises(ValueError, match="blocked_fallback"):
        select_chunk(*args, blocked_fallback="brake")
