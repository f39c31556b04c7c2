"""Formation graph: agents, edges and desired distances (paper Sec. II-A, eq. (r_G)).

The default is the paper's 4-agent team, f* = [1, 2, 1, 1, 1] (squared distances): a unit square
with one diagonal. SPEC leaves the diagonal open; we pick L2-F1 because it is the one for which the
paper's start has formation error e_d = 0.48 (the L1-F2 diagonal gives 0.40).

    L1 (-0.5, 0) ---- L2 (0.5, 0)          body frame: x to the right of the heading,
     |          /      |                    y along the heading; the midpoint sits at (0, 0)
     |       /         |
    F1 (-0.5, -1) --- F2 (0.5, -1)

Five edges on four agents in the plane is minimally rigid (Laman: 2N - 3 = 5).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

LEADERS = ("L1", "L2")


@dataclass(frozen=True)
class FormationGraph:
    """Undirected formation graph with desired distances.

    Attributes:
        agents: agent names; the first two are the leaders L1, L2 (the rigid bar), the rest followers.
        edges: pairs of agent names.
        distances: desired distance d*_ij per edge [m] (not squared).
        template: desired position of every agent in the midpoint's body frame, (N, 2) [m]; x is to
            the right of the heading, y along it. Used to place followers at the start and for
            footprint predictions.
    """

    agents: tuple[str, ...] = ("L1", "L2", "F1", "F2")
    edges: tuple[tuple[str, str], ...] = (
        ("L1", "L2"),
        ("L2", "F1"),
        ("L1", "F1"),
        ("L2", "F2"),
        ("F1", "F2"),
    )
    distances: tuple[float, ...] = (1.0, float(np.sqrt(2.0)), 1.0, 1.0, 1.0)
    template: tuple[tuple[float, float], ...] = ((-0.5, 0.0), (0.5, 0.0), (-0.5, -1.0), (0.5, -1.0))
    _index: dict[str, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if tuple(self.agents[:2]) != LEADERS:
            raise ValueError(f"the first two agents must be the leaders {LEADERS}, got {self.agents[:2]}")
        if len(set(self.agents)) != len(self.agents):
            raise ValueError(f"agent names must be unique, got {self.agents}")
        index = {name: i for i, name in enumerate(self.agents)}
        object.__setattr__(self, "_index", index)
        if len(self.edges) != len(self.distances):
            raise ValueError(f"{len(self.edges)} edges but {len(self.distances)} distances")
        for a, b in self.edges:
            for name in (a, b):
                if name not in index:
                    raise ValueError(
                        f"edge ({a}, {b}) names unknown agent {name!r}; agents are {self.agents}"
                    )
            if a == b:
                raise ValueError(f"edge ({a}, {b}) joins an agent to itself")
        for d in self.distances:
            if not np.isfinite(d) or d <= 0:
                raise ValueError(f"desired distances must be positive and finite, got {d}")
        if np.asarray(self.template).shape != (len(self.agents), 2):
            raise ValueError(
                f"template must have shape ({len(self.agents)}, 2), got {np.asarray(self.template).shape}"
            )
        if not self.is_rigid():
            raise ValueError(
                f"formation graph is not rigid: rigidity matrix rank {self.rigidity_rank()} < 2N-3 = "
                f"{2 * len(self.agents) - 3} for edges {self.edges}"
            )
        for f in range(2, len(self.agents)):
            if not np.any(self.incidence[f] != 0):
                raise ValueError(f"follower {self.agents[f]} has no edge")
        tmpl = np.asarray(self.template)
        d_tmpl = np.linalg.norm(tmpl[self.edge_i] - tmpl[self.edge_j], axis=-1)
        if not np.allclose(d_tmpl, self.distances, atol=1e-6):
            raise ValueError(f"template distances {d_tmpl} do not match desired distances {self.distances}")
        bar = np.linalg.norm(tmpl[0] - tmpl[1])
        if not np.isclose(bar, 1.0) or not np.allclose((tmpl[0] + tmpl[1]) / 2, 0.0):
            raise ValueError(f"leaders must sit at (-0.5, 0) and (0.5, 0) in the template, got {tmpl[:2]}")

    @property
    def n_agents(self) -> int:
        return len(self.agents)

    @property
    def n_followers(self) -> int:
        return len(self.agents) - 2

    @property
    def edge_i(self) -> np.ndarray:
        return np.array([self._index[a] for a, _ in self.edges])

    @property
    def edge_j(self) -> np.ndarray:
        return np.array([self._index[b] for _, b in self.edges])

    @property
    def desired_sq(self) -> np.ndarray:
        """Desired squared distances f*, (E,)."""
        return np.asarray(self.distances, dtype=np.float64) ** 2

    @property
    def incidence(self) -> np.ndarray:
        """Signed incidence, (N, E): +1 where the agent is the edge's first end, -1 at its second."""
        H = np.zeros((len(self.agents), len(self.edges)))
        H[self.edge_i, np.arange(len(self.edges))] = 1.0
        H[self.edge_j, np.arange(len(self.edges))] = -1.0
        return H

    def rigidity_rank(self, seed: int = 0) -> int:
        """Rank of the rigidity matrix R (eq. eR) at a generic (random) realisation."""
        p = np.random.default_rng(seed).normal(size=(len(self.agents), 2))
        R = np.zeros((len(self.edges), 2 * len(self.agents)))
        for k, (i, j) in enumerate(zip(self.edge_i, self.edge_j, strict=True)):
            z = p[i] - p[j]
            R[k, 2 * i : 2 * i + 2] = z
            R[k, 2 * j : 2 * j + 2] = -z
        return int(np.linalg.matrix_rank(R))

    def is_rigid(self) -> bool:
        """Generic infinitesimal rigidity in the plane: rank R = 2N - 3."""
        return self.rigidity_rank() == 2 * len(self.agents) - 3

    def radius(self) -> float:
        """Largest distance of any template agent from the midpoint [m]."""
        return float(np.max(np.linalg.norm(np.asarray(self.template), axis=-1)))

    @classmethod
    def from_dict(cls, d: dict) -> FormationGraph:
        """Build from a dict with keys agents, edges, distances and template (JSON friendly)."""
        try:
            return cls(
                agents=tuple(d["agents"]),
                edges=tuple((str(a), str(b)) for a, b in d["edges"]),
                distances=tuple(float(x) for x in d["distances"]),
                template=tuple((float(x), float(y)) for x, y in d["template"]),
            )
        except KeyError as e:
            raise ValueError(f"formation graph dict lacks key {e}; got keys {sorted(d)}") from e
