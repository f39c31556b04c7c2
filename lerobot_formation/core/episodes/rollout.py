"""Closed-loop rollouts of B episodes at once: the batched engine under the env, the vector env, the
bench and the dataset generator.

``Teams`` is the one episode path: B teams in their scenes, stepped by one ``dynamics.step`` call,
then judged by ``step_outcome`` and rewarded by ``step_reward``. ``rollout`` (the engine),
``FormationEnv`` (B = 1) and ``FormationVectorEnv`` all step through it; observations come from
``core.perception.observation``.

An episode ends on success (midpoint within ``goal_tolerance`` of the goal, no collision), on
collision (any agent disc touching any obstacle; collision wins if both happen in one step), or on
timeout after ``max_steps`` control steps. Only live episodes are stepped.

Realistic conditions (``core.perception.conditions.Conditions``: sensing range, noise, delay, rate limits,
moving obstacles) live in a ``ConditionedWorld`` that ``Teams`` builds only when some condition is on
(or its scenes give obstacle velocities); without one every step is what it was before conditions existed.

Controllers follow one interface (``core.controllers.protocol.Controller``) and see only what the
robots perceive (``core.perception.conditions.Perception``).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, fields

import numpy as np

from lerobot_formation.core.controllers.protocol import Controller
from lerobot_formation.core.encodings.obstacle_grid import environment_state, get_encoding
from lerobot_formation.core.perception.conditions import ConditionedWorld, Conditions, Perception
from lerobot_formation.core.perception.observation import observe, observe_perception
from lerobot_formation.core.world.dynamics import (
    FormationParams,
    FormationState,
    agent_positions,
    check_action,
    clip_action,
    desired_follower_positions,
    formation_error,
    initial_state,
    step,
)
from lerobot_formation.core.world.geometry import agent_clearances, midpoint_clearance, no_obstacle_as_inf
from lerobot_formation.core.world.scenes import Scenes

RUNNING, SUCCESS, COLLISION, TIMEOUT = 0, 1, 2, 3
OUTCOME_NAMES = {RUNNING: "running", SUCCESS: "success", COLLISION: "collision", TIMEOUT: "timeout"}


def step_outcome(
    state: FormationState, obstacles: np.ndarray, goal: np.ndarray, params: FormationParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(outcome (B,), agent clearances (B, N), midpoint clearance (B,)) after a step; clearances are
    +inf in a scene with no obstacle (``geometry.no_obstacle_as_inf``)."""
    clear = no_obstacle_as_inf(agent_clearances(agent_positions(state), obstacles, params.agent_radius))
    mid = no_obstacle_as_inf(midpoint_clearance(state.pose, obstacles))
    outcome = np.zeros(len(goal), dtype=np.int64)
    reached = np.linalg.norm(state.pose[:, :2] - goal, axis=-1) <= params.goal_tolerance
    outcome[reached] = SUCCESS
    outcome[(clear < 0).any(axis=1)] = COLLISION
    return outcome, clear, mid


def goal_distance(pose: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Midpoint-to-goal distance, poses (B, 3) and goals (B, 2) -> (B,). Written out (not a BLAS norm)
    so that a team's value does not depend on the batch it is in."""
    dx, dy = pose[:, 0] - goal[:, 0], pose[:, 1] - goal[:, 1]
    return np.sqrt(dx * dx + dy * dy)


def step_reward(prev_pose: np.ndarray, pose: np.ndarray, goal: np.ndarray, outcome: np.ndarray) -> np.ndarray:
    """The envs' reward (B,): progress toward the goal in metres, +1 on success, -1 on collision."""
    progress = goal_distance(prev_pose, goal) - goal_distance(pose, goal)
    return progress + (outcome == SUCCESS) - (outcome == COLLISION)


@dataclass
class Transition:
    """One control step of B teams (``Teams.step``).

    Attributes:
        prev_pose: (B, 3) midpoint poses before the step.
        action: (B, 2) the action the dynamics applied (``dynamics.step`` clips it): the checked
            command itself, or under conditions the executed velocity (delayed, noisy, rate limited).
        outcome: (B,) RUNNING, SUCCESS or COLLISION.
        reward: (B,) ``step_reward``.
        agent_clearance: (B, N) agent-disc gaps to the nearest obstacle (+inf: no obstacle).
        midpoint_clearance: (B,) midpoint to the nearest obstacle surface (+inf: no obstacle).
        command: (B, 2) the checked command as sent (the same as ``action`` without conditions).
    """

    prev_pose: np.ndarray
    action: np.ndarray
    outcome: np.ndarray
    reward: np.ndarray
    agent_clearance: np.ndarray
    midpoint_clearance: np.ndarray
    command: np.ndarray | None = None

    @property
    def terminated(self) -> np.ndarray:
        """(B,) the episode ended on success or collision."""
        return self.outcome != RUNNING


class Teams:
    """B teams in their scenes, stepped together: the one episode path (see the module docstring).

    Args:
        scenes: one scene per team (copied: ``load`` writes into the copy).
        obstacle_encoding, max_obstacles: what ``observe`` encodes (``core.perception.observation``).
        conditions: realistic conditions (``core.perception.conditions``); None or all off: none.

    Attributes:
        state: the teams' ``FormationState``; ``steps`` (B,) control steps since each team's reset.
        world: the conditions' state (``ConditionedWorld``), None when no condition is on and the
            scenes give no obstacle velocities. ``scenes`` holds the true (moving) obstacles.
    """

    def __init__(
        self,
        scenes: Scenes,
        params: FormationParams | None = None,
        obstacle_encoding: str = "grid",
        max_obstacles: int | None = None,
        conditions: Conditions | None = None,
    ):
        self.params = params or FormationParams()
        self.scenes = scenes.copy()
        self.encoding = obstacle_encoding
        self.max_obstacles = max_obstacles
        self.egocentric = get_encoding(obstacle_encoding).egocentric
        self.state = initial_state(self.scenes.start, self.params)
        self.steps = np.zeros(len(scenes), dtype=np.int64)
        self._world_state: np.ndarray | None = None  # world-frame encodings, once per scene
        conditions = conditions or Conditions()
        moving = scenes.velocities is not None and bool(np.any(scenes.velocities))
        self.world = (
            ConditionedWorld(conditions, self.scenes, self.state, self.params)
            if conditions.enabled or moving
            else None
        )
        self._perception: Perception | None = None

    def perceive(self) -> Perception:
        """What the teams perceive now (``core.perception.conditions.Perception``): the truth without conditions.
        The arrays are this step's; a caller must not write into them."""
        if self.world is None:
            return Perception.exact(self.scenes, self.state)
        if self._perception is None:
            self._perception = self.world.perceive(self.state, self.scenes)
        return self._perception

    def truth(self) -> Perception:
        """The true world (a privileged expert's view, ``ConditionedWorld.privileged``): every real
        obstacle where it is, with its velocity, the true pose, a constant map of the static ones;
        ``perceive`` without conditions."""
        if self.world is None:
            return Perception.exact(self.scenes, self.state)
        return self.world.privileged(self.state, self.scenes)

    def __len__(self) -> int:
        return len(self.scenes)

    def observe(self) -> dict[str, np.ndarray]:
        """``core.perception.observation.observe`` of every team (arrays the caller may keep): of what they
        perceive (``perceive``)."""
        if self.world is not None:
            return observe_perception(self.perceive(), self.encoding, self.max_obstacles)
        s = self.scenes
        obs = observe(
            self.state.pose,
            self.state.velocity,
            s.obstacles,
            s.mask,
            s.goal,
            self.encoding,
            self.max_obstacles,
            world_state=self._world_state,
        )
        if not self.egocentric:
            self._world_state = obs["environment_state"]
            obs["environment_state"] = self._world_state.copy()
        return obs

    def outcome(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``step_outcome`` of the teams where they stand."""
        return step_outcome(self.state, self.scenes.obstacles, self.scenes.goal, self.params)

    def step(self, action) -> Transition:
        """Validate ``action`` (B, 2) (``check_action``: a bad one changes nothing), step every team.

        Under conditions the command goes through ``ConditionedWorld.execute`` (delay, noise, rate
        limits) first; after the step the obstacles move, then the outcome is judged on where they
        are, and the teams sense and draw the next step's noise."""
        a = check_action(action, len(self))
        prev = self.state
        world = self.world
        applied = a if world is None else world.execute(a)
        self.state = step(prev, applied, self.params)
        if world is not None:
            world.move(self.scenes.obstacles)
        self.steps += 1
        outcome, clear, mid = self.outcome()
        if world is not None:
            world.sense(slice(None), self.scenes.obstacles, self.state, self.steps)
            world.draw(slice(None))
            self._perception = None
        reward = step_reward(prev.pose, self.state.pose, self.scenes.goal, outcome)
        return Transition(prev.pose, applied, outcome, reward, clear, mid, command=a)

    def truncated(self, transition: Transition, max_steps: int) -> np.ndarray:
        """(B,) the time limit ended the episode (and no success or collision did)."""
        return (self.steps >= max_steps) & ~transition.terminated

    def keep(self, rows: np.ndarray) -> None:
        """Keep only the teams ``rows`` (an index or mask), in that order: the engine drops ended ones."""
        self.state = self.state[rows]
        self.scenes = self.scenes[rows]
        self.steps = self.steps[rows]
        if self._world_state is not None:
            self._world_state = self._world_state[rows]
        if self.world is not None:
            self.world.keep(rows)
            self._perception = None

    def take(self, rows: np.ndarray) -> Teams:
        """``Teams.gather([(self, rows)])``: a new ``Teams`` of the teams ``rows`` (repeats allowed)."""
        return Teams.gather([(self, np.asarray(rows))])

    @staticmethod
    def gather(parts: list[tuple[Teams, np.ndarray]]) -> Teams:
        """A new ``Teams`` of the teams ``rows`` of each (teams, rows) part (index arrays, repeats
        allowed; the parts share params, encoding and obstacle rows), in that order: each team a copy
        with its own noise stream where it stands, which steps exactly as its original would (the
        oracle's search branches teams this way, ``core.episodes.oracle``)."""
        first = parts[0][0]
        out = copy.copy(first)
        out.state = FormationState(
            *(np.concatenate(arrays) for arrays in zip(*(t.state[r].arrays() for t, r in parts), strict=True))
        )
        out.scenes = Scenes.concat([t.scenes[r] for t, r in parts])
        out.steps = np.concatenate([t.steps[r] for t, r in parts])
        out._world_state = (
            None if first._world_state is None else np.concatenate([t._world_state[r] for t, r in parts])
        )
        out._perception = None
        if first.world is not None:
            out.world = type(first.world).gather([(t.world, r) for t, r in parts])
        return out

    def load(self, idx: np.ndarray, new: Scenes) -> None:
        """Put scenes ``new`` into the slots ``idx`` (padded to this batch's obstacle rows) and reset
        their teams: the vector env's autoreset."""
        new = new.padded(self.scenes.obstacles.shape[1])
        s = self.scenes
        s.obstacles[idx], s.mask[idx], s.goal[idx], s.start[idx], s.seeds[idx] = (
            new.obstacles,
            new.mask,
            new.goal,
            new.start,
            new.seeds,
        )
        self.state.set(idx, initial_state(new.start, self.params))
        self.steps[idx] = 0
        if self.world is not None:
            self.world.load(idx, new, initial_state(new.start, self.params))
            self._perception = None
        if self._world_state is not None:
            self._world_state[idx] = environment_state(
                new.obstacles, new.mask, new.goal, self.encoding, self.max_obstacles
            )

    def info(self, outcome: np.ndarray, clear: np.ndarray, mid: np.ndarray) -> dict[str, np.ndarray]:
        """The envs' info values (B,) for ``outcome`` and the clearances of ``step_outcome``:
        clearance (smallest agent gap) and midpoint_clearance are +inf in a scene with no obstacle."""
        return {
            "is_success": outcome == SUCCESS,
            "is_collision": outcome == COLLISION,
            "formation_error": formation_error(agent_positions(self.state), self.params.graph),
            "clearance": clear.min(axis=1),
            "midpoint_clearance": mid,
            "scene_seed": self.scenes.seeds.copy(),
        }


@dataclass
class EpisodeRecords:
    """Trajectories of B episodes, padded with NaN after each episode's end.

    Attributes:
        poses: (B, T+1, 3) midpoint poses, T = max_steps.
        actions: (B, T, 2) applied (clipped) actions.
        positions: (B, T+1, N, 2) all agents.
        formation_error: (B, T+1) e_d.
        follower_velocity_error: (B, T) mean over followers of ||v_i - v_i*||, v_i* the velocity of
            the follower's template slot.
        agent_clearance: (B, T+1) smallest agent-disc gap to any obstacle (+inf: no obstacle).
        midpoint_clearance: (B, T+1) midpoint to nearest obstacle surface (+inf: no obstacle).
        outcome: (B,) SUCCESS, COLLISION or TIMEOUT.
        steps: (B,) control steps taken.
        obstacle_paths: (B, T+1, M, 2) true obstacle centres at every frame (NaN after the episode's
            end); None without conditions.
        seen_step: (B, M) int64 control step at which each obstacle was first observed (-1: never);
            None without conditions.
        commands: (B, T, 2) the commands as sent (``actions`` are the executed ones); None without
            conditions.
        observations: ``{"agent_pos": (B, T+1, 7), "environment_state": (B, T+1, D)}`` what the
            teams observed at every frame, if ``rollout`` was asked to record them; else None.
    """

    poses: np.ndarray
    actions: np.ndarray
    positions: np.ndarray
    formation_error: np.ndarray
    follower_velocity_error: np.ndarray
    agent_clearance: np.ndarray
    midpoint_clearance: np.ndarray
    outcome: np.ndarray
    steps: np.ndarray
    dt: float = 0.1
    obstacle_paths: np.ndarray | None = None
    seen_step: np.ndarray | None = None
    commands: np.ndarray | None = None
    observations: dict[str, np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self.outcome)

    def take(self, idx) -> EpisodeRecords:
        """The episodes ``idx`` (an index array, repeats allowed, or a mask) as new records."""
        values = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "dt" or value is None:
                values[f.name] = value
            elif isinstance(value, dict):
                values[f.name] = {k: v[idx] for k, v in value.items()}
            else:
                values[f.name] = value[idx]
        return EpisodeRecords(**values)

    def put(self, idx, t: int, values: dict[str, np.ndarray]) -> None:
        """Write ``frame_record`` or ``step_record`` values of the episodes ``idx`` at time step t."""
        for key, value in values.items():
            getattr(self, key)[idx, t] = value

    @staticmethod
    def single(
        frames: list[dict[str, np.ndarray]], steps: list[dict[str, np.ndarray]], outcome: int, dt: float
    ) -> EpisodeRecords:
        """One episode's records (B = 1) from its ``frame_record`` (n + 1) and ``step_record`` (n) values."""
        values = {k: np.stack([f[k][0] for f in frames])[None] for k in frames[0]}
        if steps:
            values.update({k: np.stack([s[k][0] for s in steps])[None] for k in steps[0]})
        else:
            values.update(actions=np.zeros((1, 0, 2)), follower_velocity_error=np.zeros((1, 0)))
        return EpisodeRecords(**values, outcome=np.array([outcome]), steps=np.array([len(steps)]), dt=dt)

    def episode(self, b: int) -> dict[str, np.ndarray]:
        n = int(self.steps[b])
        return {
            "poses": self.poses[b, : n + 1],
            "actions": self.actions[b, :n],
            "positions": self.positions[b, : n + 1],
            "formation_error": self.formation_error[b, : n + 1],
            "follower_velocity_error": self.follower_velocity_error[b, :n],
            "agent_clearance": self.agent_clearance[b, : n + 1],
            "midpoint_clearance": self.midpoint_clearance[b, : n + 1],
        }


def rollout(
    scenes: Scenes,
    controller: Controller,
    params: FormationParams | None = None,
    max_steps: int | None = None,
    progress=None,
    conditions: Conditions | None = None,
    record_observations: tuple[str, int | None] | None = None,
    privileged: bool | None = None,
) -> EpisodeRecords:
    """Run ``controller`` on every scene until each episode ends, under ``conditions`` (None: none).
    ``progress(n_done)`` is called after each step if given. ``record_observations`` (encoding,
    max_obstacles): also record what the teams observe at every frame (``EpisodeRecords.observations``).
    ``privileged``: the controller acts on the true world (``Teams.truth``: a privileged expert) while
    the conditions still act on its commands and the recorded observations stay what the teams
    perceive; without conditions it changes nothing. None (default): the controller's own
    ``privileged`` attribute, if any (``data.pac_episodes.privileged_expert`` sets it), else False."""
    params = params or FormationParams()
    T = max_steps or params.max_steps
    B = len(scenes)
    N = params.graph.n_agents
    nan = np.nan
    rec = EpisodeRecords(
        poses=np.full((B, T + 1, 3), nan),
        actions=np.full((B, T, 2), nan),
        positions=np.full((B, T + 1, N, 2), nan),
        formation_error=np.full((B, T + 1), nan),
        follower_velocity_error=np.full((B, T), nan),
        agent_clearance=np.full((B, T + 1), nan),
        midpoint_clearance=np.full((B, T + 1), nan),
        outcome=np.full(B, TIMEOUT, dtype=np.int64),
        steps=np.full(B, T, dtype=np.int64),
        dt=params.dt,
    )
    encoding, slots = record_observations or ("grid", None)
    teams = Teams(scenes, params, encoding, slots, conditions)
    world = teams.world
    if world is not None:
        M = scenes.obstacles.shape[1]
        rec.obstacle_paths = np.full((B, T + 1, M, 2), nan)
        rec.obstacle_paths[:, 0] = teams.scenes.obstacles[..., :2]
        rec.seen_step = world.seen_step.copy()
        rec.commands = np.full((B, T, 2), nan)
    if record_observations is not None:
        first = teams.observe()
        rec.observations = {k: np.full((B, T + 1, v.shape[1]), nan, v.dtype) for k, v in first.items()}
        for k, v in first.items():
            rec.observations[k][:, 0] = v
    if privileged is None:  # a controller marked privileged (the bench's pac-privileged) says so itself
        privileged = bool(getattr(controller, "privileged", False))
    view = teams.truth if privileged else teams.perceive
    plan_episodes = getattr(controller, "plan_episodes", None)
    if plan_episodes is not None:  # an offline planner (the oracle) is told the episodes before they start
        plan_episodes(scenes, conditions, T)
    controller.reset(view())
    rec.put(slice(None), 0, frame_record(teams.state, scenes.obstacles, params))
    live = np.arange(B)  # the teams' episodes (global indices)
    for t in range(T):
        transition = teams.step(controller.act(view(), live))
        rec.put(live, t, step_record(transition.prev_pose, teams.state, transition.action, params))
        rec.put(live, t + 1, frame_record(teams.state, teams.scenes.obstacles, params))
        if world is not None:
            rec.obstacle_paths[live, t + 1] = teams.scenes.obstacles[..., :2]
            rec.seen_step[live] = world.seen_step
            rec.commands[live, t] = transition.command
        if rec.observations is not None:
            for k, v in teams.observe().items():
                rec.observations[k][live, t + 1] = v
        ended = transition.terminated
        rec.outcome[live[ended]] = transition.outcome[ended]
        rec.steps[live[ended]] = t + 1
        if progress is not None:
            progress(int(ended.sum()))
        if ended.any():
            live = live[~ended]
            teams.keep(~ended)
        if len(live) == 0:
            break
    if progress is not None and len(live):
        progress(len(live))
    return rec


def frame_record(
    state: FormationState, obstacles: np.ndarray, params: FormationParams
) -> dict[str, np.ndarray]:
    """What ``EpisodeRecords`` keeps of B teams at one time step: poses (B, 3), positions (B, N, 2),
    formation_error, agent_clearance and midpoint_clearance (B,) (+inf: no obstacle)."""
    pos = agent_positions(state)
    return {
        "poses": state.pose,
        "positions": pos,
        "formation_error": formation_error(pos, params.graph),
        "agent_clearance": no_obstacle_as_inf(
            agent_clearances(pos, obstacles, params.agent_radius).min(axis=1)
        ),
        "midpoint_clearance": no_obstacle_as_inf(midpoint_clearance(state.pose, obstacles)),
    }


def step_record(
    prev_pose: np.ndarray, state: FormationState, action: np.ndarray, params: FormationParams
) -> dict[str, np.ndarray]:
    """What ``EpisodeRecords`` keeps of B teams' control step from ``prev_pose`` (B, 3) to ``state``
    with ``action`` (B, 2): the applied (clipped) actions and the follower velocity error (B,), the
    mean over followers of ||v_i - v_i*||, v_i* the velocity of the follower's template slot."""
    v_des = (
        desired_follower_positions(state.pose, params.graph)
        - desired_follower_positions(prev_pose, params.graph)
    ) / params.dt  # (B, F, 2) [m/s]
    return {
        "actions": clip_action(action, params),
        "follower_velocity_error": np.linalg.norm(state.follower_vel - v_des, axis=-1).mean(-1),
    }
