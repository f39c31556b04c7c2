"""The oracle: each scene's formation path found by a best-first search in space and time on the
true simulator; a privileged reference that measures each level's ceiling, never a default.

Knowing the true world here is knowing the whole episode: the obstacles, the movers' future (they
do not react to the team) and every noise draw of the level's conditions (one stream per episode,
drawn whatever the team does; ``core.perception.conditions``). A command sequence found by stepping
copies of the episode's own teams (``rollout.Teams.gather``) therefore ends the same way when
``rollout`` replays it: the oracle plans offline (``OracleController.plan_episodes``, called by
``rollout`` before the episodes start) and acts from its plan.

The search (weighted A* over time, all scenes at once). A node is the whole episode state after a
sequence of primitives, each ``segment`` control steps long: a constant command of

    U = {(0, 0)}  U  {(s v_max, w omega_max) : s in speeds, w in turns},

or route pursuit's law (``core.controllers.route_pursuit.pursuit_command``) down the static
cost-to-go at r v_max, r in ``route_speeds``, a command at every step.

Each round pops, per scene, the ``expand`` open nodes of least

    f = t + weight * (ctg(p) / v_max + w_c * max(0, c_0 - c)),

steps each of them once with every primitive through the level's world (the followers' law, delay,
action noise, rate limits, the movers) and opens the children that did not collide. t is the node's
time [s], ctg the cost-to-go of its midpoint p to the goal on the static obstacles
(``navigation.cost_to_go``, inflated as one of ``passes`` says: progress around walls), c its smallest agent
clearance to any obstacle, movers included (``clearance_margin`` c_0 [m], ``clearance_weight`` w_c
[s/m]). A node whose cell of (x, y, heading, speed) (``cell``, ``headings``, ``SPEED_BIN``; with
moving obstacles also ``time_bin``; in the last pass also the turn rate: under rate limits a team
turning fast is not one going straight) was expanded before is dropped, so a search stuck before a
gap the square cannot pass goes back to older, other nodes instead of trying the same place again. A
scene is solved when a child reaches the goal; the search of a scene ends unsolved when its open
list empties, its nodes run out of time, or after its pass's rounds; a scene a pass leaves goes to
the next, on another inflation. It is a lower bound on what can be solved (finer primitives or more
rounds may solve more), so the ceiling it gives is conservative; the scenes it leaves are listed
with their cause (``CAUSES``).
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

from lerobot_formation.core.controllers.route_pursuit import RoutePursuitConfig, route_command
from lerobot_formation.core.encodings.encoding import world_to_body
from lerobot_formation.core.encodings.route_encoding import NEAR_CELLS
from lerobot_formation.core.episodes.rollout import COLLISION, SUCCESS, Teams
from lerobot_formation.core.perception.conditions import ConditionedWorld, Conditions, Perception
from lerobot_formation.core.world.dynamics import FormationParams, agent_positions
from lerobot_formation.core.world.geometry import obstacle_gaps
from lerobot_formation.core.world.navigation import SceneFields
from lerobot_formation.core.world.scenes import FAR, Scenes

SOLVED = "solved"
ORACLE_KEY = "oracle_cause"  # the bench results' per-episode key of the oracle's cause
ROUTE = RoutePursuitConfig()  # the route primitives' law
SPEED_BIN = 0.15  # [m/s] speed bins of the search's cells
# why the oracle left a scene: every branch collided within ``pinned_s`` of the start; the last
# branches were struck by a mover, or ran into static obstacles; time or the rounds ran out
CAUSES = (
    "pinned at the start",
    "struck by a mover",
    "no way past the static obstacles",
    "out of time",
    "search budget spent",
)


@dataclass(frozen=True)
class OracleConfig:
    """The search's budget and scoring (module docstring)."""

    expand: int = 8  # open nodes expanded per scene and round
    segment: int = 5  # control steps a primitive is held (0.5 s)
    speeds: tuple[float, ...] = (0.5, 1.0)  # fractions of v_max (and standing still)
    turns: tuple[float, ...] = (-1.0, -0.5, 0.0, 0.5, 1.0)  # fractions of omega_max
    route_speeds: tuple[float, ...] = (
        0.5,
        1.0,
    )  # route pursuit down the static cost-to-go (fractions of v_max)
    weight: float = 2.0  # > 1: greedier than A*, fewer rounds
    # the searches, in turn, each of the scenes the ones before left: (the cost-to-go's obstacle
    # inflation [m], the rounds a scene may take, the cells' turn-rate bin [rad/s] or 0: none)
    passes: tuple[tuple[float, int, float], ...] = (
        (0.65, 1000, 0.0),
        (0.5, 300, 0.0),
        (0.8, 300, 0.0),
        (0.65, 300, 0.5),
    )
    clearance_margin: float = 0.3  # [m] c_0
    clearance_weight: float = 10.0  # [s/m] w_c
    cell: float = 0.25  # [m] one expansion per cell ...
    headings: int = 8  # ... heading bin ...
    time_bin: float = 2.0  # [s] ... and, with moving obstacles, time bin (waiting is a way)
    pinned_s: float = 3.0  # [s] a search whose branches all collide this early was pinned

    def __post_init__(self) -> None:
        for name in ("expand", "segment", "headings"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"OracleConfig.{name} must be >= 1, got {getattr(self, name)}")
        if not self.speeds or not all(0 < s <= 1 for s in self.speeds):
            raise ValueError(f"OracleConfig.speeds must be fractions in (0, 1], got {self.speeds}")
        if not all(0 < s <= 1 for s in self.route_speeds):
            raise ValueError(
                f"OracleConfig.route_speeds must be fractions in (0, 1], got {self.route_speeds}"
            )
        if not self.turns or not all(-1 <= w <= 1 for w in self.turns):
            raise ValueError(f"OracleConfig.turns must be fractions in [-1, 1], got {self.turns}")
        if not self.passes or not all(
            len(p) == 3 and np.isfinite(p[0]) and p[0] >= 0 and int(p[1]) >= 1 and p[2] >= 0
            for p in self.passes
        ):
            raise ValueError(
                f"OracleConfig.passes must be (inflation >= 0, rounds >= 1, turn bin >= 0) triples, got {self.passes}"
            )
        for name in (
            "weight",
            "clearance_margin",
            "clearance_weight",
            "cell",
            "time_bin",
            "pinned_s",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"OracleConfig.{name} must be a number >= 0, got {value}")
        if self.cell <= 0 or self.time_bin <= 0:
            raise ValueError(f"OracleConfig.cell and time_bin must be > 0, got {self.cell}, {self.time_bin}")

    def primitives(self, params: FormationParams) -> np.ndarray:
        """U (P, 2) [v, omega]: standing still, then every speed with every turn."""
        moves = [(s * params.v_max, w * params.omega_max) for s in self.speeds for w in self.turns]
        return np.array([(0.0, 0.0), *moves])


@dataclass
class OraclePlans:
    """What the search found for S scenes.

    Attributes:
        commands: (S, T, 2) each scene's command sequence (zeros after its plan: standing still); an
            unsolved scene's is the plan to its node nearest the goal.
        solved: (S,) bool, a branch reached the goal.
        steps: (S,) control steps of the plan (to the goal, or to that nearest node).
        cause: (S,) ``SOLVED`` or one of ``CAUSES``.
        rounds: (S,) search rounds the scene took.
    """

    commands: np.ndarray
    solved: np.ndarray
    steps: np.ndarray
    cause: np.ndarray
    rounds: np.ndarray


class _KnownFuture(ConditionedWorld):
    """A level's world whose exogenous future is looked up instead of simulated: the movers' positions
    and velocities and the noise of every step, recorded once per scene from the world itself
    (``record``; they do not depend on what the team does), so that branching a team copies no noise
    stream and steps no mover. What the team would perceive is not kept (``sense`` does nothing): the
    oracle acts on the true world."""

    PER_TEAM = (*ConditionedWorld.PER_TEAM, "source", "clock")

    @classmethod
    def record(cls, world: ConditionedWorld, obstacles: np.ndarray, max_steps: int) -> _KnownFuture:
        """The future of ``world``'s teams in their true ``obstacles`` (B, M, 3) over ``max_steps``
        steps (neither is changed), as ``Teams.step`` would meet it: noise drawn after each move."""
        known = cls.__new__(cls)
        known.__dict__.update(vars(world))
        future = ConditionedWorld.gather([(world, np.arange(len(world.real)))])
        moving = obstacles.copy()
        B = len(moving)
        known.paths = np.empty((B, max_steps + 1, *moving.shape[1:]))
        known.velocities = np.empty((B, max_steps + 1, *future.velocity.shape[1:]))
        known.noises = np.empty((B, max_steps + 1, future.noise.shape[1]))
        known.paths[:, 0], known.velocities[:, 0], known.noises[:, 0] = moving, future.velocity, future.noise
        for t in range(1, max_steps + 1):
            future.move(moving)
            future.draw(slice(None))
            known.paths[:, t], known.velocities[:, t], known.noises[:, t] = (
                moving,
                future.velocity,
                future.noise,
            )
        known.source = np.arange(B)
        known.clock = np.zeros(B, dtype=np.int64)
        known.rngs = [None] * B
        return known

    def move(self, obstacles: np.ndarray) -> None:
        self.clock = self.clock + 1
        t = np.minimum(self.clock, self.paths.shape[1] - 1)
        obstacles[:] = self.paths[self.source, t]
        self.velocity = self.velocities[self.source, t]

    def sense(self, idx, obstacles, state, steps) -> None:
        """Nothing: the oracle perceives nothing, it knows."""

    def draw(self, idx) -> None:
        rows = np.arange(len(self.real))[idx]
        t = np.minimum(self.clock[rows], self.noises.shape[1] - 1)
        self.noise[rows] = self.noises[self.source[rows], t]


def _static_fields(teams: Teams, inflate: float) -> SceneFields:
    """The cost-to-go fields of the scenes' static obstacles (movers and padding left out)."""
    obstacles, mask = teams.scenes.obstacles, teams.scenes.mask
    static = mask if teams.world is None else mask & ~np.any(teams.world.velocity != 0, axis=-1)
    pad = np.array([FAR, FAR, 0.0])
    return SceneFields.build(np.where(static[..., None], obstacles, pad), teams.scenes.goal, inflate)


def _cost_to_go(fields: SceneFields, scene: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """ctg (R,) of points xy (R, 2), point r on the field of scene ``scene[r]``."""
    out = np.empty(len(xy))
    for s in np.unique(scene):
        rows = np.flatnonzero(scene == s)
        out[rows] = fields.fields[s].at(xy[rows], np.zeros(len(rows), dtype=np.int64), bilinear=True)
    return out


def _struck_by_mover(teams: Teams, rows: np.ndarray) -> np.ndarray:
    """(len(rows),) bool: the obstacle nearest an agent of each team ``rows`` moves."""
    if teams.world is None or len(rows) == 0:
        return np.zeros(len(rows), dtype=bool)
    gap = obstacle_gaps(agent_positions(teams.state[rows]), teams.scenes.obstacles[rows])  # (R, N, M)
    gap = np.where(teams.scenes.mask[rows][:, None], gap, np.inf).min(axis=1)  # (R, M)
    nearest = np.argmin(gap, axis=1)
    return np.any(teams.world.velocity[rows, nearest] != 0, axis=-1)


class _Nodes:
    """Every node the search opened: where its episode state lives (a batch of teams and a row), its
    parent, the commands of its segment, its scene and time step."""

    def __init__(self):
        self.batches: list[Teams] = []
        self.segments: list[np.ndarray] = []  # per batch: (n, segment, 2) the commands sent
        self.batch, self.row, self.parent, self.scene, self.step = [], [], [], [], []

    def add(self, teams: Teams, segments: np.ndarray, parent, scene, step) -> np.ndarray:
        first = len(self.batch)
        self.batches.append(teams)
        self.segments.append(segments)
        n = len(teams)
        self.batch += [len(self.batches) - 1] * n
        self.row += list(range(n))
        self.parent += list(parent)
        self.scene += list(scene)
        self.step += list(step)
        return np.arange(first, first + n)

    def gather(self, ids: np.ndarray) -> Teams:
        """The episode states of the nodes ``ids``, copied, in that order."""
        batch = np.array([self.batch[i] for i in ids])
        row = np.array([self.row[i] for i in ids])
        order = np.argsort(batch, kind="stable")
        parts = [(self.batches[b], row[order][batch[order] == b]) for b in np.unique(batch)]
        teams = Teams.gather(parts)  # the copies, grouped by batch ...
        teams.keep(np.argsort(order, kind="stable"))  # ... put back in the order asked
        return teams

    def commands(self, node: int) -> np.ndarray:
        """(steps, 2) the commands from the root to ``node``."""
        parts = []
        while self.parent[node] >= 0:  # a root sent nothing
            parts.append(self.segments[self.batch[node]][self.row[node]])
            node = self.parent[node]
        return np.concatenate(parts[::-1]) if parts else np.zeros((0, 2))


def _route_commands(
    pose: np.ndarray, goal: np.ndarray, fields: SceneFields, speed: np.ndarray, params: FormationParams
) -> np.ndarray:
    """Route pursuit's command (R, 2) from midpoint poses (R, 3) to goals (R, 2) down each row's static
    cost-to-go ``fields`` (R rows) at ``speed`` (R,) [m/s] (``core.controllers.route_pursuit.route_command``:
    its carrot, gains and slowing near the goal)."""
    target = world_to_body(fields.carrot(pose[:, :2], NEAR_CELLS), pose)
    command = route_command(target, pose, goal, ROUTE, params.omega_max)
    command[:, 0] *= speed / ROUTE.v_max
    return command


def _search(
    scenes: Scenes,
    params: FormationParams,
    conditions: Conditions | None,
    max_steps: int,
    config: OracleConfig,
    inflate: float,
    max_rounds: int,
    turn_bin: float,
) -> OraclePlans:
    """The best-first search of every scene on the cost-to-go inflated by ``inflate``, at most
    ``max_rounds`` rounds a scene, cells split by turn rate in bins of ``turn_bin`` (0: not) (module
    docstring)."""
    S, L = len(scenes), config.segment
    U = config.primitives(params)
    routes = np.array(config.route_speeds) * params.v_max  # the route primitives' speeds, after U
    P = len(U) + len(routes)
    root = Teams(scenes, params, conditions=conditions)
    if root.world is not None:
        root.world = _KnownFuture.record(root.world, root.scenes.obstacles, max_steps)
    fields = _static_fields(root, inflate)
    movers = root.world is not None and bool(np.any(root.world.velocity))
    nodes = _Nodes()
    h0 = _cost_to_go(fields, np.arange(S), root.state.pose[:, :2]) / params.v_max
    ids = nodes.add(root, np.zeros((S, 0, 2)), [-1] * S, range(S), [0] * S)
    opened: list[list] = [[(config.weight * h0[s], int(ids[s]))] for s in range(S)]  # per scene, a heap
    closed: list[set] = [set() for _ in range(S)]
    goal_node = np.full(S, -1)
    best_node, best_h = ids.copy(), h0.copy()
    cause = np.full(S, SOLVED, dtype=object)
    rounds = np.zeros(S, dtype=np.int64)
    struck = np.zeros(S)  # of the last children that collided: the share struck by a mover
    last_collision = np.zeros(S, dtype=np.int64)
    late = np.zeros(S, dtype=bool)  # some node ran out of time
    live = set(range(S))
    while live:
        pop = []
        for s in sorted(live):
            taken = 0
            while opened[s] and taken < config.expand:
                _, node = heapq.heappop(opened[s])
                x, y, phi = nodes.batches[nodes.batch[node]].state.pose[nodes.row[node]]
                v = nodes.batches[nodes.batch[node]].state.velocity[nodes.row[node]]
                key = (
                    int(np.floor(x / config.cell)),
                    int(np.floor(y / config.cell)),
                    int(np.floor(np.mod(phi, 2 * np.pi) / (2 * np.pi / config.headings))),
                    int(np.hypot(v[0], v[1]) // SPEED_BIN),
                    int(v[2] // turn_bin) if turn_bin else 0,
                    int(nodes.step[node] * params.dt // config.time_bin) if movers else 0,
                )
                if key in closed[s]:
                    continue
                closed[s].add(key)
                if nodes.step[node] + L > max_steps:
                    late[s] = True
                    continue
                pop.append(node)
                taken += 1
            rounds[s] += 1
            if taken == 0 or rounds[s] > max_rounds:
                live.discard(s)
                if rounds[s] > max_rounds:
                    cause[s] = CAUSES[4]
                elif late[s]:
                    cause[s] = CAUSES[3]
                elif last_collision[s] <= config.pinned_s / params.dt:
                    cause[s] = CAUSES[0]
                else:
                    cause[s] = CAUSES[1] if struck[s] >= 0.5 else CAUSES[2]
        if not pop:
            break
        pop = np.array(pop)
        parent = np.repeat(pop, P)
        move = np.tile(np.arange(P), len(pop))
        child = nodes.gather(parent)
        scene = np.repeat([nodes.scene[i] for i in pop], P)
        dead, done = np.zeros(len(parent), dtype=bool), np.zeros(len(parent), dtype=bool)
        by_mover = np.zeros(len(parent), dtype=bool)
        follow = move >= len(U)
        sent = np.zeros((len(parent), L, 2))
        for k in range(L):
            command = U[np.minimum(move, len(U) - 1)]
            if follow.any():
                rows = np.flatnonzero(follow)
                command[rows] = _route_commands(
                    child.state.pose[rows],
                    child.scenes.goal[rows],
                    fields[scene[rows]],
                    routes[move[rows] - len(U)],
                    params,
                )
            sent[:, k] = command
            transition = child.step(command)
            hit = (transition.outcome == COLLISION) & ~dead & ~done
            by_mover[hit] = _struck_by_mover(child, np.flatnonzero(hit))
            dead |= hit
            done |= (transition.outcome == SUCCESS) & ~dead
        step = np.repeat([nodes.step[i] for i in pop], P) + L
        for s in np.unique(scene[dead]):
            rows = dead & (scene == s)
            struck[s] = by_mover[rows].mean()
            last_collision[s] = max(last_collision[s], int(step[rows].max()))
        keep = np.flatnonzero(~dead)
        pose = child.state.pose[keep]
        clearance = transition.agent_clearance.min(axis=1)[keep]
        h = _cost_to_go(fields, scene[keep], pose[:, :2]) / params.v_max
        h = h + config.clearance_weight * np.maximum(0.0, config.clearance_margin - clearance)
        child.keep(keep)
        ids = nodes.add(child, sent[keep], parent[keep], scene[keep], step[keep])
        for node, s, d, hn in zip(ids, scene[keep], done[keep], h, strict=True):
            if s not in live:
                continue
            if d:
                goal_node[s] = node
                live.discard(s)
                continue
            if hn < best_h[s]:
                best_h[s], best_node[s] = hn, node
            heapq.heappush(opened[s], (nodes.step[node] * params.dt + config.weight * hn, int(node)))
    commands = np.zeros((S, max_steps, 2))
    steps = np.zeros(S, dtype=np.int64)
    for s in range(S):
        plan = nodes.commands(int(goal_node[s] if goal_node[s] >= 0 else best_node[s]))[:max_steps]
        commands[s, : len(plan)] = plan
        steps[s] = len(plan)
    return OraclePlans(commands, goal_node >= 0, steps, cause, rounds)


def oracle_plans(
    scenes: Scenes,
    params: FormationParams | None = None,
    conditions: Conditions | None = None,
    max_steps: int | None = None,
    config: OracleConfig | None = None,
) -> OraclePlans:
    """The oracle's plans of ``scenes`` under ``conditions`` (module docstring): a search on the
    cost-to-go of each of ``config.passes`` in turn, each of the scenes the ones before left (a gap
    the square passes only just looks closed on a field inflated too much, and a trap looks open on
    one inflated too little)."""
    params = params or FormationParams()
    config = config or OracleConfig()
    T = max_steps or params.max_steps
    plans = _search(scenes, params, conditions, T, config, *config.passes[0])
    for inflate, max_rounds, turn_bin in config.passes[1:]:
        left = np.flatnonzero(~plans.solved)
        if not len(left):
            break
        again = _search(scenes[left], params, conditions, T, config, inflate, max_rounds, turn_bin)
        plans.rounds[left] += again.rounds
        now = left[again.solved]
        plans.commands[now], plans.steps[now] = again.commands[again.solved], again.steps[again.solved]
        plans.solved[now], plans.cause[now] = True, SOLVED
    return plans


class OracleController:
    """The oracle behind the ``protocol.Controller`` interface: it plans offline when ``rollout`` hands it
    the episodes (``plan_episodes``), then replays each episode's plan; ``plans`` keeps what it found."""

    name = "oracle"
    privileged = True  # a reference on the true world, never a controller of the team's perception

    def __init__(self, config: OracleConfig | None = None, params: FormationParams | None = None):
        self.config = config or OracleConfig()
        self.params = params or FormationParams()
        self.plans: OraclePlans | None = None
        self._step = np.zeros(0, dtype=np.int64)

    def plan_episodes(self, scenes: Scenes, conditions: Conditions | None, max_steps: int) -> None:
        self.plans = oracle_plans(scenes, self.params, conditions, max_steps, self.config)
        self._step = np.zeros(len(scenes), dtype=np.int64)

    def reset(self, view: Perception) -> None:
        if self.plans is None or len(self.plans.solved) != len(view):
            raise RuntimeError(
                "the oracle plans offline: run it through core.episodes.rollout (or the bench), which "
                "hands it the episodes before they start"
            )

    def episode_notes(self) -> list[dict]:
        """Per episode, in the batch's order: why the oracle left it (``SOLVED`` or one of ``CAUSES``)
        and the search rounds it took (the bench writes them into its results)."""
        return [
            {ORACLE_KEY: str(cause), "oracle_rounds": int(rounds)}
            for cause, rounds in zip(self.plans.cause, self.plans.rounds, strict=True)
        ]

    def act(self, view: Perception, idx: np.ndarray) -> np.ndarray:
        step = np.minimum(self._step[idx], self.plans.commands.shape[1] - 1)
        self._step[idx] += 1
        return self.plans.commands[idx, step]


def make_oracle(name: str, params: FormationParams, options=None, bundle=None) -> OracleController:
    """The controller registry's factory (``bench.controllers.CONTROLLER_FACTORIES``)."""
    return OracleController(params=params)
