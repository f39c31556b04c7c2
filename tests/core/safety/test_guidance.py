"""Clearance guidance's cost and gradient (``core.safety.guidance``)."""

import numpy as np
import pytest

from lerobot_formation.core.controllers.footprint import TeamBody, sequence_clearance
from lerobot_formation.core.safety.guidance import clearance_cost_gradient
from lerobot_formation.core.world.dynamics import FormationParams

PARAMS = FormationParams()
BODY = TeamBody.of(PARAMS)


def _case(seed=0, B=2, C=3, T=12, M=6):
    rng = np.random.default_rng(seed)
    pose = np.array([[0.0, 0.0, np.pi / 2], [0.1, -0.2, 1.3]])[:B]
    actions = np.stack([rng.uniform(0.1, 0.6, (B, C, T)), rng.uniform(-1.0, 1.0, (B, C, T))], axis=-1)
    obstacles = np.concatenate([rng.uniform(-1.5, 1.5, (B, M, 2)), rng.uniform(0.2, 0.6, (B, M, 1))], axis=-1)
    return pose, actions, obstacles, rng.normal(0.0, 0.3, (B, M, 2))


@pytest.mark.parametrize("moving", [False, True])
def test_gradient_matches_central_differences(moving):
    pose, actions, obstacles, velocity = _case()
    velocity = velocity if moving else None
    radii = BODY.agent_radius + np.array([0.0, 0.0, 0.03, 0.03])  # one per agent, as the layer's followers
    body = TeamBody(BODY.template, radii, BODY.dt)

    def cost(a):
        return clearance_cost_gradient(pose, a, obstacles, body, 0.4, velocity, 1)[0]

    J, grad = clearance_cost_gradient(pose, actions, obstacles, body, 0.4, velocity, 1)
    assert (J > 0).all()  # the case does intrude
    eps = 1e-6
    numeric = np.zeros_like(grad)
    for idx in np.ndindex(actions.shape):
        up, down = actions.copy(), actions.copy()
        up[idx] += eps
        down[idx] -= eps
        numeric[idx] = (cost(up) - cost(down))[idx[:2]] / (2 * eps)
    np.testing.assert_allclose(grad, numeric, atol=1e-6)


def test_cost_is_zero_beyond_the_distance_and_a_step_down_the_gradient_clears():
    pose = np.array([[0.0, 0.0, np.pi / 2]])
    ahead = np.zeros((1, 1, 15, 2))
    ahead[..., 0] = 0.5  # straight on, 0.75 m in 1.5 s
    far = np.array([[[0.0, 5.0, 0.5]]])
    J, grad = clearance_cost_gradient(pose, ahead, far, BODY, 0.3)
    assert J[0, 0] == 0 and not grad.any()
    near = np.array([[[0.35, 1.2, 0.3]]])  # beside the right leader's path
    J, grad = clearance_cost_gradient(pose, ahead, near, BODY, 0.3)
    before, _ = sequence_clearance(pose, ahead, near, BODY)
    moved = ahead - 0.5 * grad
    J2, _ = clearance_cost_gradient(pose, moved, near, BODY, 0.3)
    after, _ = sequence_clearance(pose, moved, near, BODY)
    assert J2[0, 0] < J[0, 0] and after[0, 0] > before[0, 0]


def test_a_bad_distance_is_refused_with_its_value():
    pose, actions, obstacles, _ = _case()
    with pytest.raises(ValueError, match="guidance distance must be > 0.*-0.1"):
        clearance_cost_gradient(pose, actions, obstacles, BODY, -0.1)
