"""The safety layer: the CBF filter never makes a safe action unsafe and stops collisions; best-of-K
never keeps a colliding chunk when a safe one exists."""

import numpy as np
import pytest

from lerobot_formation.core.controllers.footprint import TeamBody
from lerobot_formation.core.encodings.obstacle_grid import environment_state
from lerobot_formation.core.safety.filters import (
    ESCAPE_PRIMITIVES,
    ESCAPE_TURN_RATES,
    FootprintCheck,
    PlanCoherence,
    barrier_rows,
    cbf_filter,
    cost_to_go_progress,
    decode_nearest,
    escape_primitives,
    plan_is_safe,
    select_chunk,
)
from lerobot_formation.core.world import dynamics
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.core.world.geometry import agent_clearances
from lerobot_formation.core.world.scenes import FAR

P = FormationParams()
NO_ESCAPES = np.zeros((0, 2))  # an empty escape lattice: the sampled candidates alone
TEMPLATE = np.asarray(P.graph.template)
BODY = TeamBody.of(P)  # the team the footprint checks move
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
    assert info["choice"][0] in (1, 2)  # never the colliding one
    assert not info["escaped"][0] and not info["blocked"][0]
    # K = 1 and safe: that candidate
    _, info1 = select_chunk(cand[:, 1:2], obstacles, goal, TEMPLATE, P.dt, P.agent_radius, 0.1)
    assert info1["choice"][0] == 0
    # none safe: a safe escape manoeuvre if there is one, else the largest clearance
    blocked = np.array([[[0.5, 0.5, 0.3], [-0.5, 0.5, 0.3]]])
    _, info2 = select_chunk(cand, blocked, goal, TEMPLATE, P.dt, P.agent_radius, 0.1)
    assert not info2["any_safe"][0]
    if not info2["escaped"][0]:
        assert info2["choice"][0] == np.argmax(info2["clearance"][0])
    _, info3 = select_chunk(cand, blocked, goal, TEMPLATE, P.dt, P.agent_radius, 0.1, primitives=NO_ESCAPES)
    assert info3["choice"][0] == np.argmax(info3["clearance"][0])


@pytest.mark.parametrize("bilinear", [False, True])
@pytest.mark.parametrize("resolution", [0.2, 0.3, 0.4])
def test_progress_goes_round_an_obstacle_not_through_it(resolution, bilinear):
    """Cost-to-go progress prefers the chunk that starts round an obstacle on the straight line over
    the one that heads at it (straight-line progress would pick the latter), on the default grid and
    on coarser ones (``progress_resolution``)."""
    obstacles = np.array([[[0.0, 3.2, 0.8]]])
    goal = np.array([[0.0, 7.0]])
    T = 16
    straight = np.tile([0.5, 0.0], (T, 1))
    veer = np.tile([0.5, 0.35], (T, 1))
    cand = np.stack([straight, veer])[None]
    _, ctg = select_chunk(
        cand,
        obstacles,
        goal,
        TEMPLATE,
        P.dt,
        P.agent_radius,
        0.1,
        progress_resolution=resolution,
        progress_bilinear=bilinear,
    )
    assert ctg["safe"][0].all()
    assert ctg["choice"][0] == 1


def test_progress_resolution_is_the_grid_cell_size():
    """``cost_to_go_progress`` reads the cost-to-go on a grid of ``resolution`` m cells: in free space
    a chunk that ends d metres nearer the goal scores d to within a cell, whatever the cell size."""
    obstacles = np.zeros((1, 1, 3))  # one empty slot
    goal = np.array([[0.0, 5.0]])
    end = np.array([[[0.0, 1.0], [0.0, 2.0], [0.0, -1.0]]])
    for resolution in (0.2, 0.3, 0.5):
        for bilinear in (False, True):
            progress = cost_to_go_progress(obstacles, goal, end, 6.0, resolution, bilinear)[0]
            np.testing.assert_allclose(progress, [1.0, 2.0, -1.0], atol=resolution)
            assert progress[1] > progress[0] > 0 > progress[2]
    # ends 5 cm apart in one cell: nearest reads tie them, bilinear reads rank them
    close = np.array([[[0.0, 1.2], [0.0, 1.25]]])
    tied = cost_to_go_progress(obstacles, goal, close, 6.0, 0.3)[0]
    ranked = cost_to_go_progress(obstacles, goal, close, 6.0, 0.3, bilinear=True)[0]
    assert tied[0] == tied[1] and ranked[1] > ranked[0]


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
    assert not info_w["any_safe"][0] and not info_w["stopped"][0] and info_w["blocked"][0]
    assert info_w["clearance"][0].max() < 0  # what "widest" keeps collides
    np.testing.assert_array_equal(widest[0], cand[0, np.argmax(info_w["clearance"][0])])
    stop, info_s = select_chunk(*args, escape_advantage=0.1, blocked_fallback="stop")
    assert info_s["stopped"][0] and not info_s["escaped"][0] and info_s["blocked"][0]
    np.testing.assert_array_equal(stop[0], np.zeros((T, 2)))
    # nothing safe, but no contact: an obstacle 0.3 m ahead of both leaders, every candidate drives
    # 0.25 m toward it (ends inside the 0.1 m margin, not in contact); without escapes it is kept
    lead_y = TEMPLATE[:, 1].max()
    ahead = np.array([[[x, lead_y + P.agent_radius + 0.3 + 0.4, 0.4] for x in (-0.6, 0.0, 0.6)]])
    slow = np.tile([0.25 / (T * P.dt), 0.0], (1, 3, T, 1))
    kept, info_k = select_chunk(
        slow, ahead, goal, TEMPLATE, P.dt, P.agent_radius, 0.1, primitives=NO_ESCAPES, blocked_fallback="stop"
    )
    assert not info_k["any_safe"][0] and not info_k["stopped"][0]
    assert 0 <= info_k["clearance"][0].max() < 0.1
    np.testing.assert_array_equal(kept[0], slow[0, 0])
    with pytest.raises(ValueError, match="blocked_fallback"):
        select_chunk(*args, blocked_fallback="brake")


# -- moving obstacles, delay and rate limits (issue 24) ---------------------------------------------


def _straight(v=0.5, steps=15):
    return np.tile([v, 0.0], (1, 1, steps, 1))  # (1, 1, T, 2)


def test_scorer_checks_a_chunk_against_where_a_moving_obstacle_will_be():
    """A straight chunk (0.75 m in 1.5 s) passes an obstacle standing 2 m to its right, but not the
    same obstacle crossing at 1.5 m/s toward the path: it meets the right leader's path (x = 0.5) at
    y = 0.6 after 1 s, when the team is there."""
    goal = np.array([[0.0, 8.0]])
    obstacles = np.array([[[2.0, 0.6, 0.2], [FAR, FAR, 0.0]]])
    crossing = np.array([[[-1.5, 0.0], [0.0, 0.0]]])
    args = (_straight(), obstacles, goal, TEMPLATE, P.dt, P.agent_radius, 0.1)
    _, standing = select_chunk(*args, primitives=NO_ESCAPES)
    _, moving = select_chunk(*args, primitives=NO_ESCAPES, obstacle_velocity=crossing)
    assert standing["safe"][0, 0] and not moving["safe"][0, 0]
    assert moving["clearance"][0, 0] < 0 < standing["clearance"][0, 0] - 0.1
    # zero velocities are the static check, bit for bit
    _, still = select_chunk(*args, primitives=NO_ESCAPES, obstacle_velocity=np.zeros_like(crossing))
    np.testing.assert_array_equal(still["clearance"], standing["clearance"])
    # moving away from the path it is no threat
    _, away = select_chunk(*args, primitives=NO_ESCAPES, obstacle_velocity=-crossing)
    assert away["safe"][0, 0]


def test_mover_uncertainty_rejects_a_close_pass_late_in_the_horizon():
    """A straight chunk passes a mover crossing at 0.3 m/s with 0.17 m predicted clearance after about
    1.5 s: safe with a 0.1 m margin as an exact prediction, not with the mover's radius grown by
    0.1 m/s (0.15 m by then). The same obstacle standing keeps every clearance: it is not moving."""
    goal = np.array([[0.0, 8.0]])
    obstacles = np.array([[[1.4, 0.6, 0.2], [FAR, FAR, 0.0]]])
    crossing = np.array([[[-0.3, 0.0], [0.0, 0.0]]])
    args = (_straight(), obstacles, goal, TEMPLATE, P.dt, P.agent_radius, 0.1)
    _, exact = select_chunk(*args, primitives=NO_ESCAPES, obstacle_velocity=crossing)
    _, unsure = select_chunk(*args, primitives=NO_ESCAPES, obstacle_velocity=crossing, mover_uncertainty=0.1)
    assert exact["safe"][0, 0] and not unsure["safe"][0, 0]
    assert 0.1 < exact["clearance"][0, 0] - unsure["clearance"][0, 0] <= 0.1 * 1.5 + 1e-9
    standing = np.zeros_like(crossing)
    _, still = select_chunk(*args, primitives=NO_ESCAPES, obstacle_velocity=standing)
    _, still_unsure = select_chunk(
        *args, primitives=NO_ESCAPES, obstacle_velocity=standing, mover_uncertainty=0.1
    )
    np.testing.assert_array_equal(still_unsure["clearance"], still["clearance"])


def test_fast_escape_manoeuvres_outrun_a_mover_coming_up_behind():
    """A wide obstacle (r 0.9 m) comes up behind the standing team at 0.45 m/s. The policy's chunk (a
    stop) is struck, and so is every manoeuvre of the default lattice (turns and arcs at <= 0.3 m/s):
    nothing is safe and the widest sampled chunk is kept. With 0.45 and 0.6 m/s in the lattice the
    team drives away at full speed."""
    goal = np.array([[0.0, 8.0]])
    obstacles = np.array([[[0.0, -2.15, 0.9], [FAR, FAR, 0.0]]])
    behind = np.array([[[0.0, 0.45], [0.0, 0.0]]])
    stop = np.zeros((1, 1, 16, 2))
    args = (stop, obstacles, goal, TEMPLATE, P.dt, P.agent_radius, 0.05)
    slow_chunk, slow = select_chunk(*args, obstacle_velocity=behind)
    assert not slow["escaped"][0] and slow["choice"][0] == 0
    np.testing.assert_array_equal(slow_chunk, stop[:, 0])
    np.testing.assert_array_equal(escape_primitives(), ESCAPE_PRIMITIVES)  # the default lattice
    lattice = escape_primitives((0.0, 0.1, 0.2, 0.3, 0.45, 0.6))
    assert len(lattice) == 6 * len(ESCAPE_TURN_RATES) - 1  # less the standstill
    fast_chunk, fast = select_chunk(*args, obstacle_velocity=behind, primitives=lattice)
    assert fast["escaped"][0]
    np.testing.assert_allclose(fast_chunk[0], np.tile([0.6, 0.0], (16, 1)))
    # nothing safe: the widest of every candidate scored (a manoeuvre struck later), not the stop
    _, widest = select_chunk(*args, obstacle_velocity=behind, fallback_all=True)
    assert widest["escaped"][0] and not slow["escaped"][0]


@pytest.mark.parametrize("with_continuation", [False, True])
def test_an_episode_with_a_safe_sample_is_scored_as_if_the_manoeuvres_were_too(with_continuation):
    """The lattice is scored only when some episode of the batch has no safe sampled chunk (a manoeuvre
    could be kept only there). Episode 0 (open road) alone skips it; beside episode 1 (a wall across
    its way, no sample safe) its lattice is scored: its choice, chunk and diagnostics are the same."""
    rng = np.random.default_rng(3)
    goal = np.array([[0.5, 6.0], [0.0, 6.0]])
    obstacles = np.array([[[3.0, 4.0, 0.4], [-2.5, 1.0, 0.5]], [[0.5, 1.0, 0.4], [-0.5, 1.0, 0.4]]])
    candidates = np.stack([np.tile([0.4, 0.0], (4, 16, 1)) + rng.normal(0, 0.05, (4, 16, 2))] * 2)
    standing = (lambda end: np.zeros(end.shape[:2] + (5, 2))) if with_continuation else None
    args = (TEMPLATE, P.dt, P.agent_radius, 0.05)
    both_chunk, both = select_chunk(candidates, obstacles, goal, *args, continuation=standing)
    one_chunk, one = select_chunk(candidates[:1], obstacles[:1], goal[:1], *args, continuation=standing)
    assert one["any_safe"][0] and not both["any_safe"][1] and both["escaped"][1]
    np.testing.assert_array_equal(both_chunk[:1], one_chunk)
    for key, value in one.items():
        np.testing.assert_array_equal(both[key][:1], value, err_msg=key)


def test_filter_counts_an_approaching_obstacle():
    """Full speed toward an obstacle 2 m ahead: standing, the barrier allows it; coming at 3 m/s, its
    rows ask v <= ~0.2 (n . v_obs added to the bound)."""
    obstacles = np.array([[[0.0, 2.0, 0.3]]])
    full = np.array([[0.6, 0.0]])
    out, changed = _filter(full, obstacles)
    assert not changed[0] and out[0, 0] == 0.6
    coming = np.array([[[0.0, -3.0]]])
    out, changed = cbf_filter(
        full, obstacles, TEMPLATE, P.agent_radius, 0.1, 2.0, LOW, HIGH, obstacle_velocity=coming
    )
    assert changed[0] and out[0, 0] < 0.25
    out, changed = cbf_filter(
        full, obstacles, TEMPLATE, P.agent_radius, 0.1, 2.0, LOW, HIGH, obstacle_velocity=-coming
    )
    assert not changed[0]  # leaving


def test_filter_with_velocities_avoids_a_crossing_obstacle_the_static_one_hits():
    """An obstacle crossing the team's way at 0.5 m/s (the team drives at 0.6 m/s, followers on the
    real follower law): the filter that takes obstacles as standing lets the team meet it; with the
    obstacle's velocity in the barrier the team waits and never touches it."""
    from lerobot_formation.core.encodings.velocity_encoding import body_velocities

    goal = np.array([[0.0, 20.0]])
    for use_velocity, expect_hit in ((False, True), (True, False)):
        obstacles = np.array([[[3.0, 1.6, 0.4], [FAR, FAR, 0.0]]])
        velocity = np.array([[[-0.5, 0.0], [0.0, 0.0]]])
        mask = np.array([[True, False]])
        state = dynamics.initial_state(np.array([[0.0, 0.0, np.pi / 2]]), P)
        hit = False
        for _ in range(60):
            env = environment_state(obstacles, mask, goal, "nearest", pose=state.pose)
            _, seen, _ = decode_nearest(env, 12)
            seen_v = np.zeros((1, 12, 2))
            seen_v[0, 0] = body_velocities(velocity, state.pose)[0, 0]  # slot 0: the only obstacle
            a, _ = cbf_filter(
                np.array([[0.6, 0.0]]),
                seen,
                TEMPLATE,
                P.agent_radius,
                0.1,
                2.0,
                LOW,
                HIGH,
                obstacle_velocity=seen_v if use_velocity else None,
            )
            state = dynamics.step(state, a, P)
            obstacles[..., :2] += velocity * P.dt
            hit |= bool(
                (agent_clearances(dynamics.agent_positions(state), obstacles, P.agent_radius) < 0).any()
            )
        assert hit == expect_hit


def test_commands_in_flight_shift_the_predicted_start():
    """Two commands of 0.5 m/s in flight move the start 0.1 m ahead (and a turn turns it); with a
    rate limit from rest they move it only as far as the limited velocities go."""
    from lerobot_formation.core.safety.filters import predict_start

    flight = np.array([[[0.5, 0.0], [0.5, 0.0]], [[0.0, 1.0], [0.0, 1.0]]])
    executed = np.array([[0.5, 0.0], [0.0, 1.0]])
    start = predict_start(flight, executed, P.dt)
    np.testing.assert_allclose(start.pose[0], [0.0, 0.1, np.pi / 2], atol=1e-12)
    np.testing.assert_allclose(start.pose[1], [0.0, 0.0, np.pi / 2 + 0.2], atol=1e-12)
    assert start.steps == 2
    slow = predict_start(flight[:1], np.zeros((1, 2)), P.dt, max_linear_accel=0.5)
    np.testing.assert_allclose(slow.velocity, [[0.1, 0.0]])  # 0.05 m/s per step
    np.testing.assert_allclose(slow.pose[0, 1], 0.1 * (0.05 + 0.1))
    none = predict_start(np.zeros((1, 0, 2)), executed[:1], P.dt)
    np.testing.assert_array_equal(none.pose, [[0.0, 0.0, np.pi / 2]])
    # the scorer starts there: standing still 0.1 m short of an obstacle is safe from now, not from
    # where the commands in flight take the team
    obstacles = np.array(
        [[[0.5, 0.45, 0.2]]]
    )  # 0.05 m from the right leader's disc edge... after 0.1 m, inside
    goal = np.array([[0.0, 8.0]])
    stop = np.zeros((1, 1, 15, 2))
    args = (stop, obstacles, goal, TEMPLATE, P.dt, P.agent_radius, 0.0)
    _, now = select_chunk(*args, primitives=NO_ESCAPES)
    _, late = select_chunk(*args, primitives=NO_ESCAPES, start=start[:1])
    assert now["clearance"][0, 0] > 0.1 and late["clearance"][0, 0] == pytest.approx(
        now["clearance"][0, 0] - 0.1
    )
    # the filter too: the right leader's barrier (h = 0.25 m now, 0.15 m after the commands in flight)
    # bounds its closing speed v + 0.5 omega by alpha h: 0.5 from now, 0.3 from the predicted start
    near = np.array([[[0.5, 0.75, 0.3]]])
    free, _ = _filter(np.array([[0.6, 0.0]]), near)
    braked, changed = cbf_filter(
        np.array([[0.6, 0.0]]), near, TEMPLATE, P.agent_radius, 0.1, 2.0, LOW, HIGH, start=start[:1]
    )
    closing = lambda u: u[0, 0] + 0.5 * u[0, 1]  # noqa: E731
    assert changed[0] and closing(free) == pytest.approx(0.5) and closing(braked) == pytest.approx(0.3)


def test_rate_limits_in_the_forward_model():
    """Braking from 0.6 m/s with 0.5 m/s^2 takes 1.2 s (0.36 m): a stop chunk that is safe for an
    actuator without limits meets an obstacle 0.25 m ahead when the actuator is rate limited. The
    limited rollout is ``rate_limit`` step by step."""
    from lerobot_formation.core.safety.filters import ChunkStart

    commands = np.random.default_rng(0).uniform([0.0, -1.5], [0.6, 1.5], (2, 3, 15, 2))
    previous = np.array([[0.3, 0.0], [0.6, 1.0]])
    run = dynamics.rate_limit_sequence(previous, commands, 0.5, 2.0, P.dt)
    now = np.repeat(previous, 3, axis=0)
    for k in range(15):
        now = dynamics.rate_limit(now, commands[:, :, k].reshape(6, 2), 0.5, 2.0, P.dt)
        np.testing.assert_array_equal(run[:, :, k].reshape(6, 2), now)
    assert dynamics.rate_limit_sequence(previous, commands, None, None, P.dt) is commands
    obstacles = np.array([[[0.5, 0.45, 0.1]]])  # 0.25 m ahead of the right leader's disc
    goal = np.array([[0.0, 8.0]])
    stop = np.zeros((1, 1, 15, 2))
    rolling = ChunkStart(np.array([[0.0, 0.0, np.pi / 2]]), np.array([[0.6, 0.0]]))
    limited = ChunkStart(rolling.pose, rolling.velocity, 0, 0.5, None)
    _, free = select_chunk(
        stop, obstacles, goal, TEMPLATE, P.dt, P.agent_radius, 0.1, primitives=NO_ESCAPES, start=rolling
    )
    _, slow = select_chunk(
        stop, obstacles, goal, TEMPLATE, P.dt, P.agent_radius, 0.1, primitives=NO_ESCAPES, start=limited
    )
    assert free["safe"][0, 0] and not slow["safe"][0, 0] and slow["clearance"][0, 0] < 0


def test_filter_chooses_among_reachable_velocities():
    """With a rate limit the filter's box is what one step can reach from the executed velocity: a
    command the limit alone changes is no intervention (returned as commanded), and a barrier asking
    for more braking than reachable gets the hardest reachable braking."""
    from lerobot_formation.core.safety.filters import ChunkStart

    start = ChunkStart(np.array([[0.0, 0.0, np.pi / 2]]), np.array([[0.6, 0.0]]), 0, 0.5, 2.0)
    far = np.array([[[FAR, FAR, 0.0]]])
    stop = np.array([[0.0, 0.0]])
    out, changed = cbf_filter(stop, far, TEMPLATE, P.agent_radius, 0.1, 2.0, LOW, HIGH, start=start)
    assert not changed[0] and (out == stop).all()
    close = np.array([[[0.5, 0.55, 0.2]]])  # the right leader's barrier asks v + 0.5 omega <= 0.3
    out, changed = cbf_filter(
        np.array([[0.6, 0.0]]), close, TEMPLATE, P.agent_radius, 0.1, 2.0, LOW, HIGH, start=start
    )
    assert changed[0]
    np.testing.assert_allclose(out[0], [0.55, -0.2])  # one step's reach: 0.05 m/s, 0.2 rad/s


def test_continuation_rejects_a_chunk_that_ends_where_the_team_cannot_turn():
    """A chunk that stops 10 cm short of a wall is safe on its own; the turn the team must make after
    it (here a turn in place, which swings a leader forward into the wall) is not, so with that
    ``continuation`` it is rejected and the chunk that stops earlier is kept. It is a preference:
    where no candidate's continuation is safe, the chunks alone decide."""
    wall = np.array([[[x, 1.6, 0.3] for x in (-1.5, -0.9, -0.3, 0.3, 0.9, 1.5)]])  # surface at 1.3 m
    goal = np.array([[0.0, 6.0]])
    T = 10
    far = np.tile([1.1 / (T * P.dt), 0.0], (1, 1, T, 1))  # 1.1 m ahead: 10 cm short of the wall
    short = np.tile([0.3, 0.0], (1, 1, T, 1))  # 0.3 m ahead
    chunks = np.concatenate([far, short], axis=1)

    def turn(end):  # (B, P, 3) -> a quarter turn in place
        return np.broadcast_to([0.0, 1.5], end.shape[:2] + (10, 2)).copy()

    alone, info = select_chunk(
        chunks, wall, goal, TEMPLATE, P.dt, P.agent_radius, 0.05, primitives=NO_ESCAPES
    )
    assert info["safe"][0].all() and info["choice"][0] == 0  # the farther one: more progress
    kept, info = select_chunk(
        chunks, wall, goal, TEMPLATE, P.dt, P.agent_radius, 0.05, primitives=NO_ESCAPES, continuation=turn
    )
    assert not info["safe"][0, 0] and info["safe"][0, 1] and info["choice"][0] == 1

    def ram(end):  # every continuation hits the wall: the chunks alone decide, as without one
        return np.broadcast_to([0.6, 0.0], end.shape[:2] + (30, 2)).copy()

    kept, info = select_chunk(
        chunks, wall, goal, TEMPLATE, P.dt, P.agent_radius, 0.05, primitives=NO_ESCAPES, continuation=ram
    )
    assert info["safe"][0].all() and info["choice"][0] == 0


def test_a_plan_checked_again_fails_once_a_mover_heads_for_its_path():
    """The rest of a straight plan (0.3 m/s, 1 s) passes an obstacle 1.5 m to its right while it
    stands, not once it is seen crossing toward the path at 1.2 m/s; with a continuation (0.9 m
    more ahead) the same plan fails on a wall it does not reach itself. Each verdict is best-of-K's
    on the same sequence (``select_chunk``'s "safe" for it alone)."""
    plan = np.tile([0.3, 0.0], (1, 10, 1))
    obstacles = np.array([[[2.0, 0.2, 0.3], [FAR, FAR, 0.0]]])
    crossing = np.array([[[-1.2, 0.0], [0.0, 0.0]]])
    assert plan_is_safe(plan, FootprintCheck(obstacles, BODY), 0.1)[0]
    assert not plan_is_safe(plan, FootprintCheck(obstacles, BODY, obstacle_velocity=crossing), 0.1)[0]
    for velocity in (None, crossing):
        _, info = select_chunk(
            plan[:, None], obstacles, np.array([[0.0, 8.0]]), TEMPLATE, P.dt, P.agent_radius, 0.1,
            primitives=NO_ESCAPES, obstacle_velocity=velocity,
        )  # fmt: skip
        check = FootprintCheck(obstacles, BODY, obstacle_velocity=velocity)
        assert info["safe"][0, 0] == plan_is_safe(plan, check, 0.1)[0]
    wall = np.array([[[x, 1.45, 0.3] for x in (-1.2, -0.6, 0.0, 0.6, 1.2)]])  # surface at 1.15 m
    ahead = lambda end: np.broadcast_to([0.6, 0.0], end.shape[:2] + (15, 2)).copy()  # noqa: E731
    wall_args = (wall, BODY)
    assert plan_is_safe(plan, FootprintCheck(*wall_args), 0.05)[0]
    assert not plan_is_safe(plan, FootprintCheck(*wall_args, continuation=ahead), 0.05)[0]
    # batched: each plan its own verdict
    both = FootprintCheck(np.concatenate([obstacles, obstacles]), BODY,
                          np.concatenate([np.zeros_like(crossing), crossing]))  # fmt: skip
    np.testing.assert_array_equal(plan_is_safe(np.concatenate([plan, plan]), both, 0.1), [True, False])


def test_the_lookahead_runs_only_after_sequences_that_keep_the_floor():
    """``footprint(commands, floor)`` rolls the continuation out only after the sequences whose own
    clearance keeps the floor: for those the numbers are those of the full rollout, bit for bit
    (rows of different counts padded); the others report their own clearance and end pose."""
    rng = np.random.default_rng(5)
    obstacles = np.array([[[0.5, 1.2, 0.3], [-1.0, 2.5, 0.4]], [[2.0, 2.0, 0.3], [FAR, FAR, 0.0]]])
    velocity = np.array([[[0.0, -0.2], [0.1, 0.0]], [[0.0, 0.0], [0.0, 0.0]]])
    commands = np.stack([np.tile([0.4, 0.0], (12, 16, 1)) + rng.normal(0, [0.15, 0.6], (12, 16, 2))] * 2)

    def ahead(end):  # (B, P, 3) -> straight on at 0.3 m/s, turning with the heading's sine
        return np.stack(np.broadcast_arrays(0.3, np.sin(end[..., 2:3]) + np.zeros((1, 1, 10))), -1)

    check = FootprintCheck(obstacles, BODY, velocity, continuation=ahead)
    floor = np.array([[0.05], [0.05]])
    clear, viable, end = check.footprint(commands)
    clear2, viable2, end2 = check.footprint(commands, floor)
    keep = clear >= floor
    assert 0 < keep[0].sum() < 12 and keep[0].sum() != keep[1].sum()  # ragged rows
    np.testing.assert_array_equal(clear2, clear)
    np.testing.assert_array_equal(viable2[keep], viable[keep])
    np.testing.assert_array_equal(end2[keep], end[keep])
    np.testing.assert_array_equal(viable2[~keep], clear[~keep])
    own_end = check.footprint(commands, np.full((2, 1), np.inf))[2]  # nothing kept: the sequences' ends
    np.testing.assert_array_equal(end2[~keep], own_end[~keep])
    assert not np.array_equal(own_end[keep], end[keep])


def test_coherence_keeps_the_candidate_closest_to_the_plan_it_replaces():
    """Two safe chunks in open space, straight ahead and a gentle left arc: on progress alone the
    straight one wins; with the previous plan an arc and a coherence weight above the progress gap,
    the arc is kept. Rows without a previous plan, a zero weight, and unsafe candidates are left as
    progress and safety alone decide."""
    obstacles = np.array([[[FAR, FAR, 0.0]]])
    goal = np.array([[0.0, 6.0]])
    straight = np.tile([0.5, 0.0], (1, 1, 15, 1))
    arc = np.tile([0.5, 0.3], (1, 1, 15, 1))
    chunks = np.concatenate([straight, arc], axis=1)
    args = (chunks, obstacles, goal, TEMPLATE, P.dt, P.agent_radius, 0.05)
    _, info = select_chunk(*args, primitives=NO_ESCAPES)
    assert info["choice"][0] == 0
    gap = info["progress"][0, 0] - info["progress"][0, 1]
    assert 0 < gap < 0.5
    ranges = np.array([0.6, 3.0])
    previous = np.tile([0.5, 0.3], (1, 8, 1))
    kept, info = select_chunk(
        *args, primitives=NO_ESCAPES, coherence=PlanCoherence(previous, np.array([True]), ranges, 10.0)
    )
    assert info["choice"][0] == 1 and np.allclose(kept, arc[:, 0])
    for has, weight in ((False, 10.0), (True, 0.0)):
        _, info = select_chunk(
            *args, primitives=NO_ESCAPES, coherence=PlanCoherence(previous, np.array([has]), ranges, weight)
        )
        assert info["choice"][0] == 0
    # coherence never makes an unsafe chunk safe: an obstacle the arc grazes keeps the straight one
    wall = np.array([[[-0.9, 0.6, 0.2], [FAR, FAR, 0.0]]])
    blocked = (chunks, wall, goal, TEMPLATE, P.dt, P.agent_radius, 0.05)
    _, alone = select_chunk(*blocked, primitives=NO_ESCAPES)
    assert alone["safe"][0, 0] and not alone["safe"][0, 1]
    _, info = select_chunk(
        *blocked, primitives=NO_ESCAPES, coherence=PlanCoherence(previous, np.array([True]), ranges, 10.0)
    )
    assert info["choice"][0] == 0


def test_a_per_agent_radius_widens_the_followers_discs_only():
    """One radius per template agent: equal radii give the scalar's numbers; a larger follower radius
    lowers the clearance (and the barrier value h) where a follower is the nearest agent, and leaves it
    where a leader is."""
    from lerobot_formation.core.controllers.footprint import template_clearance

    poses = np.array([[[0.0, 0.0, np.pi / 2]]])
    follower_side = np.array([[[0.5, -1.6, 0.3]]])  # behind the right follower (template y = -1)
    leader_side = np.array([[[0.5, 1.0, 0.3]]])  # in front of the right leader
    radii = np.full(len(TEMPLATE), P.agent_radius)
    for obs in (follower_side, leader_side):
        np.testing.assert_allclose(
            template_clearance(poses, obs, TEMPLATE, radii),
            template_clearance(poses, obs, TEMPLATE, P.agent_radius),
        )
    radii[2:] += 0.03
    base = template_clearance(poses, follower_side, TEMPLATE, P.agent_radius)
    np.testing.assert_allclose(template_clearance(poses, follower_side, TEMPLATE, radii), base - 0.03)
    np.testing.assert_allclose(
        template_clearance(poses, leader_side, TEMPLATE, radii),
        template_clearance(poses, leader_side, TEMPLATE, P.agent_radius),
    )
    _, _, h0 = barrier_rows(follower_side, TEMPLATE, P.agent_radius, 0.05, 2.0)
    _, _, h1 = barrier_rows(follower_side, TEMPLATE, radii, 0.05, 2.0)
    np.testing.assert_allclose(h0 - h1, [[0.0, 0.0, 0.03, 0.03]])  # rows agent-major: leaders, followers
    with pytest.raises(ValueError, match=r"one per template agent 4, got \(3,\)"):
        template_clearance(poses, follower_side, TEMPLATE, radii[:3])


def test_halt_lookahead_keeps_a_chunk_after_which_the_team_may_stop():
    """A mover (r 0.4 m) comes straight down at 0.6 m/s, 3 m ahead of the right leader. A slow right
    arc makes the most progress toward the goal (ahead, to the right) and keeps the margin over its
    own 1.6 s, but a team that stops where it ends is struck within 2 s more
    (``FootprintCheck.halted``); with ``halt_lookahead`` 20 the chunk after which the team may stop
    is kept (here the stop: the mover has not reached it 3.6 s ahead), with the same "safe" verdicts
    of the chunks alone where no candidate passes the halt either."""
    goal = np.array([[2.0, 8.0]])
    obstacles = np.array([[[0.5, 3.0, 0.4], [FAR, FAR, 0.0]]])
    down = np.array([[[0.0, -0.6], [0.0, 0.0]]])
    commands = [[0.0, 0.0], [0.3, 0.0], [0.3, -1.0], [0.3, 1.0]]  # stop, straight, right arc, left arc
    chunks = np.array([[np.tile(c, (16, 1)) for c in commands]])
    args = (chunks, obstacles, goal, TEMPLATE, P.dt, P.agent_radius, 0.05)
    _, alone = select_chunk(*args, primitives=NO_ESCAPES, obstacle_velocity=down)
    assert alone["safe"][0].all() and alone["choice"][0] == 2  # the right arc: the most progress
    halted = FootprintCheck(obstacles, BODY, down).halted(chunks, 20)
    assert halted[0, 0] >= 0.05 and (halted[0, 1:] < 0.05).all()
    kept, info = select_chunk(*args, primitives=NO_ESCAPES, obstacle_velocity=down, halt_lookahead=20)
    assert info["choice"][0] == 0 and info["safe"][0].tolist() == [True, False, False, False]
    np.testing.assert_array_equal(kept[0], chunks[0, 0])
    # nothing passes the halt (a faster mover): the chunks alone decide, as without it
    fast = 2 * down
    _, none = select_chunk(*args, primitives=NO_ESCAPES, obstacle_velocity=fast, halt_lookahead=20)
    _, plain = select_chunk(*args, primitives=NO_ESCAPES, obstacle_velocity=fast)
    assert (FootprintCheck(obstacles, BODY, fast).halted(chunks, 20) < 0.05).all()
    for key in ("choice", "safe", "clearance", "progress"):
        np.testing.assert_array_equal(none[key], plain[key])


def test_halt_lookahead_brakes_as_the_actuator_brakes_and_changes_nothing_where_a_continuation_passes():
    """``halted`` is the chunk's clearance followed by zero commands: against standing obstacles and
    without rate limits the chunk's own clearance, bit for bit. With a 0.5 m/s^2 limit a chunk at
    0.6 m/s that ends 0.2 m short of a wall needs 0.36 m to stop: halted, it reaches the wall. Where
    some candidate passes with its continuation, ``halt_lookahead`` changes nothing."""
    from lerobot_formation.core.safety.filters import ChunkStart

    rng = np.random.default_rng(7)
    obstacles = np.array([[[0.5, 2.0, 0.3], [-1.5, 1.0, 0.4]], [[2.0, 2.0, 0.3], [FAR, FAR, 0.0]]])
    commands = np.stack([np.tile([0.4, 0.0], (6, 12, 1)) + rng.normal(0, [0.1, 0.5], (6, 12, 2))] * 2)
    commands[..., 0] = np.clip(commands[..., 0], 0.0, 0.6)
    check = FootprintCheck(obstacles, BODY)
    np.testing.assert_array_equal(check.halted(commands, 10), check.footprint(commands)[0])
    np.testing.assert_array_equal(
        check.halted(commands[1:], 10, np.array([1])), check.halted(commands, 10)[1:]
    )
    wall = np.array([[[x, 1.6, 0.3] for x in (-1.5, -0.9, -0.3, 0.3, 0.9, 1.5)]])  # surface at 1.3 m
    run = np.tile([0.6, 0.0], (1, 1, 17, 1))  # 1.02 m ahead at full speed: 0.18 m short of the wall
    rolling = ChunkStart(np.array([[0.0, 0.0, np.pi / 2]]), np.array([[0.6, 0.0]]), 0, 0.5, None)
    braked = FootprintCheck(wall, BODY, start=rolling)
    assert braked.footprint(run)[0][0, 0] >= 0.05 and braked.halted(run, 20)[0, 0] < 0.0
    # a continuation that passes somewhere: the halt is never consulted
    goal = np.array([[0.0, 6.0], [0.0, 6.0]])
    stand = lambda end: np.zeros(end.shape[:2] + (5, 2))  # noqa: E731
    args = (commands, obstacles, goal, TEMPLATE, P.dt, P.agent_radius, 0.05)
    _, with_halt = select_chunk(*args, continuation=stand, halt_lookahead=20)
    _, without = select_chunk(*args, continuation=stand)
    assert with_halt["any_safe"].all()
    for key in ("choice", "safe", "clearance", "progress"):
        np.testing.assert_array_equal(with_halt[key], without[key])
