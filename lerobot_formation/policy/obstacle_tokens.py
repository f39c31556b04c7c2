"""The obstacle-token encoder of ``formation_diffusion`` (``obstacle_encoder="tokens"``): each observed
obstacle is a token, the team an ego token that attends to them, as SARL reads a crowd (Chen et al.
2019, "Crowd-Robot Interaction"). The feature does not depend on the slots' order or on how many are
filled, and an empty slot contributes nothing.

It reads an encoding of the "nearest" family (``token_layout``) in metres (the policy's ENV
normalisation is IDENTITY). Per observation step, with S slots, environment state e and the
(normalised) midpoint state s::

    goal   g   = e[0:2]                                         (body frame)
    slot k     = (x_k, y_k, r_k, p_k) = e[2 + 4k : 6 + 4k]      p_k = 1 present, 0 empty
    velocity   = (vx_k, vy_k) = e[2 + 4S + 2k : 4 + 4S + 2k]    (0 if the encoding has none)
    route  h   = the R trailing values                          (R = 0 or 5)

    obstacle token  o_k = [x_k, y_k, r_k, vx_k, vy_k, |(x_k, y_k)| - r_k]   (0 where p_k = 0)
                    z_k = MLP_o(o_k)                          in R^d
    ego token       q   = MLP_e([s, g, h])                    in R^d
    each layer      q  <- q + W_o concat_j sum_{k: p_k = 1} a_jk V_j z_k,
                           a_jk = softmax_{k: p_k = 1}(Q_j LN(q) . K_j z_k / sqrt(d / H))
                    q  <- q + FF(LN(q))
                    (the attention term is 0 where no slot is present)
    pooled          m   = max_{k: p_k = 1} z_k  (elementwise; 0 where no slot is present)
    feature         f   = [q, m]                              in R^{2d}

with H = ``TOKEN_HEADS`` heads. The policy conditions its U-Net on [s, f] per step, flattened over the
observation steps as LeRobot flattens [s, e].
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

TOKEN_HEADS = 4
OBSTACLE_FEATURES = 6  # x_b, y_b, r, vx_b, vy_b, |c| - r


@dataclass(frozen=True)
class TokenLayout:
    """Where the goal, the slots, their velocities and the route hint sit in ``environment_state``."""

    slots: int
    velocities: bool
    route: int

    @property
    def dim(self) -> int:
        return 2 + (4 + 2 * self.velocities) * self.slots + self.route


def token_layout(encoding, max_obstacles: int | None = None) -> TokenLayout | None:
    """The layout of an ``ObstacleEncoding`` of the "nearest" family (goal [x_b, y_b], then slots
    [x_b, y_b, r, present], optionally each slot's [vx_b, vy_b], optionally trailing route values),
    or None for any other encoding."""
    if (encoding.fixed, encoding.per_slot) != (2, 4) or encoding.trailing_per_slot not in (0, 2):
        return None
    slots = encoding.slots(max_obstacles)
    if slots < 1:
        return None
    return TokenLayout(slots, encoding.trailing_per_slot == 2, encoding.trailing)


def _mlp(n_in: int, dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, dim), nn.Mish(), nn.Linear(dim, dim))


class EgoAttention(nn.Module):
    """One layer: the ego token attends to the present obstacle tokens (pre-norm residual attention,
    then a feed-forward block)."""

    def __init__(self, dim: int, heads: int = TOKEN_HEADS):
        super().__init__()
        self.heads = heads
        self.norm = nn.LayerNorm(dim)
        self.query = nn.Linear(dim, dim)
        self.key = nn.Linear(dim, dim)
        self.value = nn.Linear(dim, dim)
        self.out = nn.Linear(dim, dim)
        self.ff_norm = nn.LayerNorm(dim)
        self.ff = nn.Sequential(nn.Linear(dim, 2 * dim), nn.Mish(), nn.Linear(2 * dim, dim))

    def forward(self, ego: Tensor, tokens: Tensor, present: Tensor) -> Tensor:
        """ego (N, d), tokens (N, S, d), present (N, S) bool -> ego (N, d)."""
        N, S, d = tokens.shape
        h = self.heads
        q = self.query(self.norm(ego)).view(N, h, 1, d // h)
        k = self.key(tokens).view(N, S, h, d // h).transpose(1, 2)
        v = self.value(tokens).view(N, S, h, d // h).transpose(1, 2)
        scores = (q @ k.transpose(-1, -2)) * (d // h) ** -0.5  # (N, h, 1, S)
        # the lowest finite score, not -inf: a row with no obstacle stays finite (and is zeroed below);
        # elsewhere an empty slot's weight underflows to exactly 0
        scores = scores.masked_fill(~present[:, None, None, :], torch.finfo(scores.dtype).min)
        attended = (scores.softmax(-1) @ v).reshape(N, d)
        any_present = present.any(-1, keepdim=True)
        ego = ego + torch.where(any_present, self.out(attended), 0.0)
        return ego + self.ff(self.ff_norm(ego))


class ObstacleTokenEncoder(nn.Module):
    """(state (B, T, state_dim), environment state (B, T, layout.dim)) -> (B, T, 2 dim) features
    [ego token, max-pooled obstacle tokens] (module docstring)."""

    def __init__(self, state_dim: int, layout: TokenLayout, dim: int = 64, layers: int = 1):
        super().__init__()
        self.layout = layout
        self.out_dim = 2 * dim
        self.obstacle = _mlp(OBSTACLE_FEATURES, dim)
        self.ego = _mlp(state_dim + 2 + layout.route, dim)
        self.attention = nn.ModuleList(EgoAttention(dim) for _ in range(layers))

    def split(self, env: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """environment state (N, D) -> goal (N, 2), obstacle features (N, S, 6) (zeros in empty
        slots, whatever they hold), present (N, S) bool, route (N, R)."""
        S = self.layout.slots
        rows = env[:, 2 : 2 + 4 * S].reshape(-1, S, 4)
        present = rows[..., 3] > 0.5
        if self.layout.velocities:
            velocity = env[:, 2 + 4 * S : 2 + 6 * S].reshape(-1, S, 2)
        else:
            velocity = torch.zeros_like(rows[..., :2])
        centre, radius = rows[..., :2], rows[..., 2:3]
        surface = torch.linalg.vector_norm(centre, dim=-1, keepdim=True) - radius
        features = torch.cat([centre, radius, velocity, surface], dim=-1)
        features = torch.where(present[..., None], features, 0.0)
        route = env[:, env.shape[-1] - self.layout.route :]
        return env[:, :2], features, present, route

    def forward(self, state: Tensor, env: Tensor) -> Tensor:
        lead = state.shape[:-1]
        state, env = state.reshape(-1, state.shape[-1]), env.reshape(-1, env.shape[-1])
        goal, features, present, route = self.split(env)
        tokens = self.obstacle(features)  # (N, S, d)
        ego = self.ego(torch.cat([state, goal, route], dim=-1))
        for layer in self.attention:
            ego = layer(ego, tokens, present)
        lowest = torch.finfo(tokens.dtype).min
        pooled = tokens.masked_fill(~present[..., None], lowest).amax(dim=1)
        pooled = torch.where(present.any(-1, keepdim=True), pooled, 0.0)
        return torch.cat([ego, pooled], dim=-1).reshape(*lead, self.out_dim)
