"""Planning over achieved states: a graph of where options have actually taken the agent.

Nodes are voxels of the subgoal space (edge length ``resolution``) that some option started or ended in; a directed
edge joins the voxel an option started in to the voxel it ended in. Edges are facts about reached states (as the
primitive-in-the-loop labels are), so the graph never asks the current lower level for anything, and paths through it
stitch pieces of different trajectories together.

:meth:`SubgoalGraph.plan` walks ``lookahead`` edges along a shortest path (in options) from the voxel of the
current achieved goal toward the goal: toward the goal's own voxel, or, if no option ever ended there, toward the
visited voxel nearest to it (within ``2 * resolution``), from where the lower level covers the last stretch. It says
per row whether it planned: a row is planned exactly where a path is known from the current voxel to a different goal
node. Callers act on that flag, never on whether a waypoint differs from the goal (the goal itself is a planned
waypoint once the path reaches it, and a goal that went through a normaliser or a float32 copy differs from itself).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.common.trajectories import TrajectoryBuffer

DictObs = dict[str, np.ndarray]
EdgeCheck = Callable[[DictObs, np.ndarray], np.ndarray]


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
