"""Planning over achieved states: a graph of where options have actually taken the agent.

Nodes are voxels of the subgoal space (edge length ``resolution``) that some option started or ended in; a directed
edge joins the voxel an option started in to the voxel it ended in. Edges are facts about reached states (as the
primitive-in-the-loop labels are), so the graph never asks the current lower level for anything, and paths through it
stitch pieces of different trajectories together.
The graph knows places only, not what else the observation holds: on a task whose obstacles move between episodes
(the random Fetch mazes draw a new layout at every reset) it joins edges that options took in different layouts, and a
path through it may cross a wall of the current one.

:meth:`SubgoalGraph.plan` walks ``lookahead`` edges along a shortest path (in options) from the voxel of the
current achieved goal toward the goal: toward the goal's own voxel, or, if no option ever ended there, toward the
visited voxel nearest to it (within ``2 * resolution``), from where the lower level covers the last stretch. It says
per row whether it planned: a row is planned exactly where a path is known from the current voxel to a different goal
node. Callers act on that flag, never on whether a waypoint differs from the goal (the goal itself is a planned
waypoint once the path reaches it, and a goal that went through a normaliser or a float32 copy differs from itself).

:class:`SubgoalPlanner` is what a higher level that proposes subgoals plans with (DIPPER's ``planner_kwargs``): it
owns the graph and its settings, rebuilds the graph as trajectories finish, and steers the policy's proposals in
training and, if asked, in :meth:`predict`.
"""

from __future__ import annotations

import warnings
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.common.trajectories import TrajectoryBuffer
from sb3_dipper.common.validation import as_bool, as_int, as_optional_float

if TYPE_CHECKING:
    from sb3_dipper.common.low_level import SubgoalNormalizer

DictObs = dict[str, np.ndarray]
EdgeCheck = Callable[[DictObs, np.ndarray], np.ndarray]
# ``lower_value(start_observations, target_points) -> values``: the lower level's value of reaching each target point
# (a subgoal, world units) from each start state (original observations).
LowerValue = Callable[[DictObs, np.ndarray], np.ndarray]
# Policy proposals for a batch of (normalised) observations: higher-level actions in ``[-1, 1]^d``, ``(n, d)``.
Proposals = Callable[[DictObs], np.ndarray]

PLANNING_MODES = ("off", "subgoal", "waypoint")
# Rebuild the planning graph after this many new trajectories (a rebuild takes milliseconds).
GRAPH_REBUILD_TRAJECTORIES = 4


class Plan(NamedTuple):
    """What the planner proposes for a batch of rows."""

    #: ``(n, d)`` float32: the waypoint of each planned row, the goal (as given) elsewhere
    waypoints: np.ndarray
    #: ``(n,)`` bool: whether the planner knew a path for the row and proposes its waypoint
    planned: np.ndarray


class SubgoalGraph:
    """Voxel graph of option transitions, with breadth-first distances to goals.

    :param subgoal_space: the space the voxels tile
    :param resolution: voxel edge length in world units
    """

    def __init__(self, subgoal_space: SubgoalSpace, resolution: float) -> None:
        if resolution <= 0:
            raise ValueError(f"The planning resolution must be positive, got {resolution}")
        self.subgoal_space = subgoal_space
        self.resolution = float(resolution)
        self.grid_shape = tuple(int(n) for n in np.maximum(np.ceil((subgoal_space.high - subgoal_space.low) / resolution), 1))
        self.node_ids = np.zeros(0, dtype=np.int64)
        self.node_points = np.zeros((0, subgoal_space.dim), dtype=np.float32)
        self.edges = np.zeros((0, 2), dtype=np.int64)
        self._index: dict[int, int] = {}
        self._predecessors: list[list[int]] = []
        self._successors: list[list[int]] = []
        self._distances: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return int(self.node_ids.size)

    def has_voxels_of(self, subgoal_space: SubgoalSpace, resolution: float) -> bool:
        """Whether its voxels are those of ``resolution`` over ``subgoal_space``."""
        return self.resolution == float(resolution) and self.subgoal_space.same_as(subgoal_space)

    def __getstate__(self) -> dict:
        # The distance cache is recomputed on demand; saved models do not need to carry it.
        return {**self.__dict__, "_distances": {}}

    def voxel_ids(self, points: np.ndarray) -> np.ndarray:
        """Flat voxel index of each point (points outside the space fall in the border voxels)."""
        cells = np.floor((points - self.subgoal_space.low) / self.resolution).astype(np.int64)
        cells = np.clip(cells, 0, np.array(self.grid_shape) - 1)
        return np.ravel_multi_index(tuple(np.moveaxis(cells, -1, 0)), self.grid_shape)

    def rebuild(self, buffer: TrajectoryBuffer, edge_check: EdgeCheck | None = None) -> None:
        """Rebuild nodes and edges from every stored trajectory.

        :param edge_check: keeps an edge only if it accepts at least one option that took it:
            ``edge_check(start_observations, target_points) -> keep`` (for example: the lower level's value of
            reaching the target voxel from the option's start state is high enough)
        """
        n_trajectories = len(buffer)
        if n_trajectories == 0:
            return
        space = self.subgoal_space
        starts = space.project(buffer.observations["achieved_goal"][:n_trajectories, :1])
        ends = space.project(buffer.next_achieved_goals[:n_trajectories])
        points = np.concatenate([starts, ends], axis=1)
        valid = np.concatenate([np.ones((n_trajectories, 1), dtype=bool), buffer.mask(np.arange(n_trajectories))], axis=1)
        ids = self.voxel_ids(points)
        edge_valid = valid[:, 1:] & (ids[:, 1:] != ids[:, :-1])
        sources, targets = ids[:, :-1][edge_valid], ids[:, 1:][edge_valid]
        self.set_nodes(ids[valid], points[valid])
        if edge_check is not None and sources.size > 0:
            trajectory, step = np.nonzero(edge_valid)
            start_observations = {key: value[trajectory, step] for key, value in buffer.observations.items()}
            keep = edge_check(start_observations, self.node_points[[self._index[int(voxel)] for voxel in targets]])
            sources, targets = sources[keep], targets[keep]
        self.set_edges(np.unique(np.stack([sources, targets], axis=1), axis=0))

    def set_nodes(self, point_ids: np.ndarray, points: np.ndarray) -> None:
        """Set the nodes from points and their voxel ids (a node's point is the mean of its points); no edges."""
        self.node_ids, inverse = np.unique(point_ids, return_inverse=True)
        counts = np.bincount(inverse, minlength=self.node_ids.size).astype(np.float64)
        sums = np.stack(
            [np.bincount(inverse, weights=points[:, dim], minlength=self.node_ids.size) for dim in range(points.shape[1])], 1
        )
        self.node_points = (sums / counts[:, None]).astype(np.float32)
        self._index = {int(voxel): node for node, voxel in enumerate(self.node_ids)}
        self.set_edges(np.zeros((0, 2), dtype=np.int64))

    def set_edges(self, voxel_edges: np.ndarray) -> None:
        """Set the directed edges, given as pairs of voxel ids of existing nodes."""
        self.edges = np.array([[self._index[int(a)], self._index[int(b)]] for a, b in voxel_edges], dtype=np.int64).reshape(
            -1, 2
        )
        self._successors = [[] for _ in range(len(self))]
        self._predecessors = [[] for _ in range(len(self))]
        for source, target in self.edges:
            self._successors[source].append(int(target))
            self._predecessors[target].append(int(source))
        self._distances = {}

    def distances_to(self, node: int) -> np.ndarray:
        """Options needed from every node to ``node`` along known edges (``inf`` where there is no path)."""
        if node not in self._distances:
            distances = np.full(len(self), np.inf)
            distances[node] = 0.0
            queue = deque([node])
            while queue:
                current = queue.popleft()
                for previous in self._predecessors[current]:
                    if distances[previous] == np.inf:
                        distances[previous] = distances[current] + 1.0
                        queue.append(previous)
            self._distances[node] = distances
        return self._distances[node]

    def goal_node(self, goal: np.ndarray) -> int | None:
        """The node of the goal's voxel, else the node nearest to the goal within two voxels, else ``None``."""
        node = self._index.get(int(self.voxel_ids(goal[None])[0]))
        if node is not None:
            return node
        distances = np.linalg.norm(self.node_points - goal, axis=-1)
        nearest = int(np.argmin(distances))
        return nearest if distances[nearest] <= 2 * self.resolution else None

    def plan(self, achieved: np.ndarray, goals: np.ndarray, lookahead: int) -> Plan:
        """For each row, the point ``lookahead`` options along a shortest known path to the goal, and whether there is one.

        A row is not planned (its waypoint is the goal as given) where the graph is empty, the current voxel or the
        goal has no node, the current voxel is the goal's node, or no path leads from one to the other. Along a path,
        the waypoint is the goal itself once the walk reaches the goal's own (visited) voxel, else the mean point of
        the node the walk reached.
        """
        waypoints = np.array(goals, dtype=np.float32, copy=True)
        planned = np.zeros(waypoints.shape[0], dtype=bool)
        if len(self) == 0:
            return Plan(waypoints, planned)
        start_ids = self.voxel_ids(achieved)
        for row, start_voxel in enumerate(start_ids):
            start, goal = self._index.get(int(start_voxel)), self.goal_node(waypoints[row])
            if start is None or goal is None or start == goal:
                continue
            distances = self.distances_to(goal)
            if distances[start] == np.inf:
                continue
            planned[row] = True
            current = start
            for _ in range(lookahead):
                current = min(self._successors[current], key=lambda node: distances[node])
                if current == goal:
                    break
            goal_voxel_visited = int(self.node_ids[goal]) == int(self.voxel_ids(waypoints[row : row + 1])[0])
            if current != goal or not goal_voxel_visited:
                waypoints[row] = self.node_points[current]
        return Plan(waypoints, planned)


class SubgoalPlanner:
    """Planning over achieved states for a higher level that proposes subgoals: a :class:`SubgoalGraph` and when and how
    its waypoints steer the policy's proposals.

    Per row, :meth:`plan` gives the waypoint toward the goal and whether the graph knew a path (:class:`Plan`), and
    :meth:`propose` acts on it: with ``mode="subgoal"`` a planned row's subgoal is its waypoint, every other row's the
    policy's proposal; with ``mode="waypoint"`` the policy proposes every subgoal, a planned row's toward its waypoint
    in place of the goal. The graph is rebuilt from the stored trajectories every
    :data:`GRAPH_REBUILD_TRAJECTORIES` finished ones (:meth:`trajectories_finished`). It is saved with the model.

    :param mode: ``"off"`` (no planning), ``"subgoal"`` (where the graph knows a path to the goal, the waypoint on it
        is the subgoal; elsewhere the policy proposes) or ``"waypoint"`` (the policy always proposes, conditioned on the
        waypoint instead of the goal)
    :param lookahead: how many options along the shortest known path the waypoint lies
    :param resolution: voxel size of the graph (default: the subgoal threshold)
    :param value_threshold: keep a graph edge only if the lower level's value of reaching its target voxel from the
        start of some option that took it is at least this (``None``: keep all)
    :param in_predict: whether :meth:`plan` plans outside training (evaluation, deployment) as in training.
        ``False`` (only with ``mode="subgoal"``): the planner steers the training proposals, and the policy alone
        proposes every subgoal when the model is used
    """

    def __init__(
        self,
        mode: str = "off",
        lookahead: int = 1,
        resolution: float | None = None,
        value_threshold: float | None = None,
        in_predict: bool = True,
    ) -> None:
        if mode not in PLANNING_MODES:
            raise ValueError(f"Unknown planning mode {mode!r}: choose one of {PLANNING_MODES}")
        in_predict = as_bool("in_predict", in_predict)
        if not in_predict and mode != "subgoal":
            raise ValueError(
                f"in_predict=False needs mode='subgoal' (the planner replaces the policy's proposals in training only), "
                f"got mode={mode!r}"
            )
        self.mode = mode
        self.lookahead = as_int("lookahead", lookahead, 1)
        self.resolution = as_optional_float("resolution", resolution, 0.0, low_open=True)
        self.value_threshold = as_optional_float("value_threshold", value_threshold)
        self.in_predict = in_predict
        self.subgoal_space: SubgoalSpace | None = None
        self.graph: SubgoalGraph | None = None
        self._trajectories_since_rebuild = 0

    def __getstate__(self) -> dict[str, Any]:
        # A loaded planner counts the trajectories toward its next rebuild from zero.
        return {**self.__dict__, "_trajectories_since_rebuild": 0}

    def setup(self, subgoal_space: SubgoalSpace) -> None:
        """Plan in ``subgoal_space``: an empty graph, unless the planner has one (a saved model's) with its voxels.

        A saved graph whose voxels are not those of the settings (``planner_kwargs`` given to ``load`` with another
        ``resolution``, or another subgoal space) is replaced by an empty one, with a warning: its voxels cannot be
        redrawn without the trajectories, and it is rebuilt from the stored ones after
        :data:`GRAPH_REBUILD_TRAJECTORIES` more. With ``mode="off"`` the planner keeps no graph.
        """
        self.subgoal_space = subgoal_space
        resolution = self.resolution or subgoal_space.threshold
        if self.graph is not None and self.mode != "off" and not self.graph.has_voxels_of(subgoal_space, resolution):
            warnings.warn(
                f"planner_kwargs: the saved planning graph has voxels of {self.graph.resolution:g} over "
                f"{self.graph.subgoal_space.describe()}, the settings ask for {resolution:g} over "
                f"{subgoal_space.describe()}; it is replaced by an empty graph, rebuilt from the stored trajectories "
                f"after {GRAPH_REBUILD_TRAJECTORIES} more (nothing is planned until then)",
                stacklevel=2,
            )
            self.graph = None
        if self.mode == "off":
            self.graph = None
        elif self.graph is None:
            self.graph = SubgoalGraph(subgoal_space, resolution)
        self._trajectories_since_rebuild = 0

    @property
    def proposes_subgoals(self) -> bool:
        """Whether its waypoints replace the policy's proposals in the planned rows (``mode="subgoal"``)."""
        return self.mode == "subgoal"

    @property
    def settings(self) -> dict[str, Any]:
        """Its constructor's arguments (the ``planner_kwargs`` that build it again)."""
        return dict(
            mode=self.mode,
            lookahead=self.lookahead,
            resolution=self.resolution,
            value_threshold=self.value_threshold,
            in_predict=self.in_predict,
        )

    @property
    def plans_in_predict(self) -> bool:
        """Whether :meth:`plan` plans outside training (then a policy exported without the graph would act otherwise)."""
        return self.graph is not None and self.in_predict

    def trajectories_finished(self, count: int, buffer: TrajectoryBuffer, lower_value: LowerValue) -> None:
        """``count`` more trajectories finished in ``buffer``: rebuild the graph from it once enough have.

        :param lower_value: the lower level's values that ``value_threshold`` compares (called only with a threshold)
        """
        self._trajectories_since_rebuild += count
        if self.graph is None or self._trajectories_since_rebuild < GRAPH_REBUILD_TRAJECTORIES:
            return
        threshold = self.value_threshold
        edge_check = None if threshold is None else lambda starts, targets: lower_value(starts, targets) >= threshold
        self.graph.rebuild(buffer, edge_check)
        self._trajectories_since_rebuild = 0

    def plan(self, observation: DictObs, normalizer: SubgoalNormalizer | None, training: bool) -> Plan:
        """The waypoint toward each row's goal (world units) and whether the graph planned the row: never without a
        graph, nor outside training without ``in_predict``.

        :param observation: a batch of observations as the env returns them
        :param normalizer: what normalised the observation's goals (``None``: nothing did)
        :param training: whether the proposals are collected for training
        """
        assert self.subgoal_space is not None, "setup() gives the planner its subgoal space"
        achieved, desired = observation["achieved_goal"], observation["desired_goal"]
        if normalizer is not None:
            achieved = normalizer.unnormalize_goal(achieved, "achieved_goal")
            desired = normalizer.unnormalize_goal(desired, "desired_goal")
        space = self.subgoal_space
        goals = space.project(desired)
        if self.graph is None or not (training or self.in_predict):
            return Plan(np.array(goals, dtype=np.float32, copy=True), np.zeros(goals.shape[0], dtype=bool))
        return self.graph.plan(space.project(achieved), goals, self.lookahead)

    def propose(
        self, observation: DictObs, proposals: Proposals, normalizer: SubgoalNormalizer | None, training: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """The higher-level actions for ``observation``: the policy's ``proposals``, steered by :meth:`plan`.

        :param observation: a batch of observations as the env returns them
        :param proposals: the policy's actions for a batch of observations (with ``mode="waypoint"`` it gets the
            observation with each planned row's goal replaced by its waypoint)
        :param normalizer: what normalised the observation's goals (``None``: nothing did)
        :param training: whether the proposals are collected for training
        :return: the actions in ``[-1, 1]^d``, and which rows' subgoal is the planner's waypoint (only with
            ``mode="subgoal"``; with ``"waypoint"`` the policy proposes every subgoal)
        """
        assert self.subgoal_space is not None, "setup() gives the planner its subgoal space"
        plan = self.plan(observation, normalizer, training)
        policy_input = self._with_waypoints_as_goals(observation, plan, normalizer) if self.mode == "waypoint" else observation
        actions = proposals(policy_input)
        if not self.proposes_subgoals:
            return actions, np.zeros(actions.shape[0], dtype=bool)
        actions[plan.planned] = self.subgoal_space.to_unit(plan.waypoints[plan.planned])
        return actions, plan.planned

    def _with_waypoints_as_goals(self, observation: DictObs, plan: Plan, normalizer: SubgoalNormalizer | None) -> DictObs:
        """The observation with each planned row's goal replaced by its waypoint; the other rows are the observation's
        own."""
        assert self.subgoal_space is not None
        space, rows = self.subgoal_space, plan.planned
        if not rows.any():
            return observation
        goals = np.array(observation["desired_goal"], copy=True)
        planned = goals[rows] if normalizer is None else normalizer.unnormalize_goal(goals[rows], "desired_goal")
        planned[..., list(space.indices) if space.indices is not None else slice(None)] = plan.waypoints[rows]
        goals[rows] = planned if normalizer is None else normalizer.normalize_goal(planned, "desired_goal")
        return {**observation, "desired_goal": goals}
