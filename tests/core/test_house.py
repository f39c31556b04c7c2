"""Invariants and parities of the shared pieces: the cost-to-go, candidate scoring, PAC's footprint,
the dataset's observations, the vector env and a non-square formation graph."""

import gymnasium as gym
import numpy as np
import pytest

from lerobot_formation.core.controllers.footprint import TeamBody, sequence_clearance
from lerobot_formation.core.controllers.pac import PACController, PathAwareController
from lerobot_formation.core.episodes.rollout import rollout
from lerobot_formation.core.world import dynamics
from lerobot_formation.core.world.formation_graph import FormationGraph
from lerobot_formation.core.world.geometry import agent_clearances
from lerobot_formation.core.world.navigation import _SHIFTS, cost_to_go, cost_to_go_at
from lerobot_formation.core.world.presets import SCENE_PRESETS
from lerobot_formation.core.world.sampling import sample_scenes
from lerobot_formation.core.world.scene_files import scenes_from_list
from lerobot_formation.data.dataset_frames import episode_frames
from lerobot_formation.envs.env import FormationEnv
from lerobot_formation.envs.vector_env import FormationVectorEnv

TEMPLATE = np.asarray(FormationGraph().template)


def _scenes():
    """Paper scenes and gate scenes (narrow passages, goals in other directions)."""
    return [sample_scenes(np.arange(6)), sample_scenes(np.arange(4), SCENE_PRESETS["gates"])]


# -- cost-to-go -------------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs", [{}, {"inflate": 0.9, "wall_cost": 3.0}])
def test_cost_to_go_is_zero_at_goal_and_has_no_local_minima(kwargs):
    for scenes in _scenes():
        ctg = cost_to_go(scenes.obstacles, scenes.goal, **kwargs)
        B, n = ctg.value.shape[:2]
        assert np.array_equal(ctg.at(scenes.goal), np.zeros(B))
        assert np.isfinite(ctg.value).all()  # walls cost more but are never impassable
        padded = np.pad(ctg.value, ((0, 0), (1, 1), (1, 1)), constant_values=np.inf)
        best_neighbour = np.min(
            [padded[:, 1 + dx : 1 + dx + n, 1 + dy : 1 + dy + n] for dx, dy in _SHIFTS], axis=0
        )
        goal = np.zeros_like(ctg.value, dtype=bool)
        gi = ctg.cell(scenes.goal)
        goal[np.arange(B), gi[:, 0], gi[:, 1]] = True
        assert (best_neighbour[~goal] < ctg.value[~goal]).all()  # every cell but the goal descends


@pytest.mark.parametrize("bilinear", [False, True])
@pytest.mark.parametrize(
    "kwargs",
    [
        {},
        {"inflate": 0.9, "wall_cost": 3.0, "bounds": (-7.0, 7.0)},
        {"resolution": 0.3, "bounds": (-7.0, 7.0)},
    ],
)
def test_cost_to_go_at_equals_the_whole_field_bit_for_bit(kwargs, bilinear):
    """The early-stopping query reads the same values as the converged field, at points near and far
    from the goal, inside inflated zones and at the grid's edge, at the nearest cell or bilinearly."""
    rng = np.random.default_rng(3)
    for scenes in _scenes():
        B = len(scenes)
        field = cost_to_go(scenes.obstacles, scenes.goal, **kwargs)
        P = 40
        points = np.concatenate(
            [
                rng.uniform(-3, 9, (B, P - 3, 2)),
                scenes.goal[:, None],  # value 0
                scenes.obstacles[:, :1, :2],  # an obstacle's centre: deep in a wall
                np.full((B, 1, 2), 50.0),  # beyond the grid: its edge cell
            ],
            axis=1,
        ).reshape(B * P, 2)
        rows = np.repeat(np.arange(B), P)
        got = cost_to_go_at(scenes.obstacles, scenes.goal, points, rows, bilinear=bilinear, **kwargs)
        assert np.array_equal(got, field.at(points, rows, bilinear))
        # one scene alone (its own grid: the bounds follow the batch's goals), default rows
        zeros = np.zeros(P, dtype=int)
        one = cost_to_go_at(
            scenes.obstacles[:1], scenes.goal[:1], points[:P], zeros, bilinear=bilinear, **kwargs
        )
        field = cost_to_go(scenes.obstacles[:1], scenes.goal[:1], **kwargs)
        assert np.array_equal(one, field.at(points[:P], zeros, bilinear))
        # default rows: point p reads scene p
        first = points.reshape(B, P, 2)[:, 0]
        assert np.array_equal(
            cost_to_go_at(scenes.obstacles, scenes.goal, first, bilinear=bilinear, **kwargs),
            cost_to_go(scenes.obstacles, scenes.goal, **kwargs).at(first, None, bilinear),
        )


def test_bilinear_reads_interpolate_the_four_cells_around_a_point():
    """A bilinear read equals the nearest read at a cell's centre, the mean of two cells half-way
    between them, and is continuous across a cell border, where the nearest read jumps."""
    obstacles = np.array([[[2.0, 3.0, 0.5]]])
    goal = np.array([[0.0, 6.0]])
    field = cost_to_go(obstacles, goal, resolution=0.3, bounds=(-7.0, 7.0))
    lo, res = field.origin, field.resolution
    centre = np.array([[lo + 10 * res, lo + 12 * res]])
    assert field.at(centre, bilinear=True)[0] == field.at(centre)[0]
    between = centre + [[0.5 * res, 0.0]]
    right = centre + [[res, 0.0]]
    np.testing.assert_allclose(
        field.at(between, bilinear=True), 0.5 * (field.at(centre) + field.at(right)), rtol=1e-12
    )
    border = centre + [[0.5 * res, 0.3 * res]]
    eps = np.array([[1e-6, 0.0]])
    near = field.at(border - eps)[0], field.at(border + eps)[0]
    smooth = field.at(border - eps, bilinear=True)[0], field.at(border + eps, bilinear=True)[0]
    assert near[0] != near[1] and abs(smooth[0] - smooth[1]) < 1e-4


# -- candidate scoring ------------------------------------------------------------------------------
def _candidates(rng, B, K, T=12):
    return np.stack([rng.uniform(0, 0.6, (B, K, T)), rng.uniform(-1.5, 1.5, (B, K, T))], axis=-1)


# -- PAC's footprint --------------------------------------------------------------------------------
def test_pac_footprint_equals_shared_clearance_of_held_actions():
    """PAC's governor (closed-form poses of a held action) against ``sequence_clearance`` of the same
    action repeated, and against a plain loop: ``step_midpoint``, ``rotate_body``, ``agent_clearances``."""
    rng = np.random.default_rng(2)
    scenes = _scenes()[0]
    B, C = len(scenes), 7
    pac = PathAwareController()
    pac.reset(scenes.obstacles, scenes.goal)
    T, dt, radius = pac.config.horizon, pac.params.dt, pac.params.agent_radius
    pose = np.column_stack([rng.uniform(0, 5, (B, 2)), rng.uniform(-np.pi, np.pi, B)])
    cand = _candidates(rng, B, C, 1)[:, :, 0]  # (B, C, 2)
    got = pac.footprint_clearance(pose, cand)
    body = TeamBody(TEMPLATE, radius, dt)
    shared, _ = sequence_clearance(pose, np.repeat(cand[:, :, None], T, axis=2), scenes.obstacles, body)
    np.testing.assert_allclose(got, shared, rtol=0, atol=1e-9)
    p = np.repeat(pose[:, None], C, axis=1)  # (B, C, 3)
    loop = np.full((B, C), np.inf)
    for _ in range(T):
        p = dynamics.step_midpoint(p, cand, dt)
        agents = dynamics.rotate_body(
            np.broadcast_to(TEMPLATE, (B, C, *TEMPLATE.shape)), p[..., 2:].repeat(4, -1)
        )
        agents = agents + p[..., None, :2]  # (B, C, N, 2)
        clear = agent_clearances(agents.reshape(B, -1, 2), scenes.obstacles, radius).reshape(B, C, -1)
        loop = np.minimum(loop, clear.min(axis=-1))
    np.testing.assert_allclose(got, loop, rtol=0, atol=1e-9)


# -- the dataset's observations ---------------------------------------------------------------------
@pytest.mark.parametrize("encoding", ["grid", "nearest"])
def test_dataset_observations_equal_the_envs_over_an_episode(encoding):
    """``episode_frames`` (the dataset's ``observation.*``) and ``FormationEnv``'s observation, the env
    stepped with the recorded actions of the same (batched) PAC rollout."""
    scenes = sample_scenes([3, 4])
    rec = rollout(scenes, PACController())
    for b in range(len(scenes)):
        frames = episode_frames(rec, scenes, b, encoding)
        env = FormationEnv(obstacle_encoding=encoding)
        obs, _ = env.reset(seed=int(scenes.seeds[b]))
        n = int(rec.steps[b])
        assert len(frames["observation.state"]) == n
        for t in range(n):
            np.testing.assert_array_equal(frames["observation.state"][t], obs["agent_pos"], err_msg=f"t={t}")
            np.testing.assert_array_equal(
                frames["observation.environment_state"][t], obs["environment_state"]
            )
            obs, _, terminated, _, _ = env.step(rec.actions[b, t])
            assert np.array_equal(env.state.pose[0], rec.poses[b, t + 1])
        assert terminated


# -- vector env -------------------------------------------------------------------------------------
def _same_info(single: dict, vector: dict, i: int) -> None:
    for key, value in single.items():
        v = vector[key][i]
        if value is None:  # the single env's "no obstacle" is the vector env's NaN
            assert np.isnan(v), key
        else:
            assert value == v, (key, value, v)


def test_vector_env_matches_single_envs_in_terminated_truncated_and_info():
    """Collision, success and time limit in one batch, then autoreset: every step's observation,
    reward, terminated, truncated and info (``final_obs`` / ``final_info`` at an episode's end)."""
    limit = 25
    scenes = scenes_from_list(
        [
            {"obstacles": [[0.5, 1.5, 0.3]], "goal": [0.0, 4.0]},  # ahead of L2: a collision
            {"obstacles": [[4.0, 4.0, 0.5]], "goal": [0.0, 1.2]},  # a success after 15 steps
            {"obstacles": [], "goal": [0.0, 9.0]},  # the time limit, with no obstacle at all
        ]
    )
    B = len(scenes)
    venv = FormationVectorEnv(B, max_episode_steps=limit)
    singles = [gym.wrappers.TimeLimit(FormationEnv(), limit) for _ in range(B)]
    vobs, vinfo = venv.reset(seed=0, options={"scenes": scenes})
    for i, env in enumerate(singles):
        obs, info = env.reset(options={"scene": scenes[i]})
        np.testing.assert_array_equal(vobs["agent_pos"][i], obs["agent_pos"])
        _same_info(info, vinfo, i)
    action = np.array([0.6, 0.0], np.float32)
    ends = set()
    for _ in range(2 * limit):
        vobs, vrew, vterm, vtrunc, vinfo = venv.step(np.tile(action, (B, 1)))
        for i, env in enumerate(singles):
            obs, rew, term, trunc, info = env.step(action)
            assert (vterm[i], vtrunc[i], vrew[i]) == (term, trunc, rew)
            if term or trunc:
                ends.add(("success" if info["is_success"] else "collision") if term else "timeout")
                np.testing.assert_array_equal(vinfo["final_obs"]["agent_pos"][i], obs["agent_pos"])
                _same_info(info, vinfo["final_info"], i)
                obs, info = env.reset(options={"scene": venv.scenes[i]})  # the vector env's next scene
            else:
                _same_info(info, vinfo, i)
            np.testing.assert_array_equal(vobs["agent_pos"][i], obs["agent_pos"])
            np.testing.assert_array_equal(vobs["environment_state"][i], obs["environment_state"])
    assert ends == {"collision", "success", "timeout"}


# -- a formation graph that is not the square -------------------------------------------------------
def _graph(template, edges) -> FormationGraph:
    names = ("L1", "L2", *(f"F{i}" for i in range(1, len(template) - 1)))
    t = dict(zip(names, np.asarray(template, dtype=np.float64), strict=True))
    distances = tuple(float(np.linalg.norm(t[a] - t[b])) for a, b in edges)
    return FormationGraph(names, tuple(edges), distances, tuple(map(tuple, template)))


@pytest.mark.parametrize(
    ("graph", "start"),
    [
        # a triangle: one follower behind the bar
        (
            _graph(
                [(-0.5, 0.0), (0.5, 0.0), (0.0, -np.sqrt(3) / 2)], [("L1", "L2"), ("L1", "F1"), ("L2", "F1")]
            ),
            ((0.3, -1.2),),
        ),
        # three followers: the square with a tail (2N - 3 = 7 edges)
        (
            _graph(
                [(-0.5, 0.0), (0.5, 0.0), (-0.5, -1.0), (0.5, -1.0), (0.0, -1.5)],
                [
                    ("L1", "L2"),
                    ("L1", "F1"),
                    ("L2", "F2"),
                    ("F1", "F2"),
                    ("L2", "F1"),
                    ("F1", "F3"),
                    ("F2", "F3"),
                ],
            ),
            ((-0.2, -0.8), (0.7, -1.2), (0.2, -1.9)),
        ),
    ],
)
def test_non_square_graph_followers_close_the_formation_error(graph, start):
    params = dynamics.FormationParams(
        graph=graph, follower_start=start, follower_start_heading=(0.0,) * len(start)
    )
    state = dynamics.initial_state(np.array([[0.0, 0.0, np.pi / 2]]), params)
    errors = [dynamics.formation_error(dynamics.agent_positions(state), graph)[0]]
    for _ in range(40):  # 4 s of a gentle left arc
        state = dynamics.step(state, np.array([[0.3, 0.2]]), params)
        errors.append(dynamics.formation_error(dynamics.agent_positions(state), graph)[0])
    assert state.follower_pos.shape == (1, graph.n_followers, 2)
    assert errors[0] > 0.4
    assert max(errors[10:]) < 0.2 * errors[0]  # closed within 1 s, and it stays closed
