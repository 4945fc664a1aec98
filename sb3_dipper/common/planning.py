"""Planning over achieved states: a graph of where options have actually taken the agent.

Nodes are voxels of the subgoal space (edge length ``resolution``) that some option started or ended in; a directed
edge joins the voxel an option started in to the voxel it ended in. Edges are facts about reached states (as the
primitive-in-the-loop labels are), so the graph never asks the current lower level for anything, and paths through it
stitch pieces of different trajectories together.

:meth:`SubgoalGraph.waypoints` walks ``lookahead`` edges along a shortest path (in options) from the voxel of the
current achieved goal toward the voxel of the goal. A higher-level policy conditioned on that waypoint instead of the
far goal only has to solve a short-horizon problem, which preference learning does well; the graph supplies the long
horizon. Where no path is known, the goal itself is returned and the policy explores as usual.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.common.trajectories import TrajectoryBuffer


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

    def voxel_ids(self, points: np.ndarray) -> np.ndarray:
        """Flat voxel index of each point (points outside the space fall in the border voxels)."""
        cells = np.floor((points - self.subgoal_space.low) / self.resolution).astype(np.int64)
        cells = np.clip(cells, 0, np.array(self.grid_shape) - 1)
        return np.ravel_multi_index(tuple(np.moveaxis(cells, -1, 0)), self.grid_shape)

    def rebuild(self, buffer: TrajectoryBuffer) -> None:
        """Rebuild nodes and edges from every stored trajectory."""
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
        raw_edges = np.unique(np.stack([ids[:, :-1][edge_valid], ids[:, 1:][edge_valid]], axis=1), axis=0)
        self.set_graph(ids[valid], points[valid], raw_edges)

    def set_graph(self, point_ids: np.ndarray, points: np.ndarray, voxel_edges: np.ndarray) -> None:
        """Set the graph from points (with their voxel ids) and voxel-id edges; node points are the voxel means."""
        self.node_ids, inverse = np.unique(point_ids, return_inverse=True)
        counts = np.bincount(inverse, minlength=self.node_ids.size).astype(np.float64)
        sums = np.stack(
            [np.bincount(inverse, weights=points[:, dim], minlength=self.node_ids.size) for dim in range(points.shape[1])], 1
        )
        self.node_points = (sums / counts[:, None]).astype(np.float32)
        self._index = {int(voxel): node for node, voxel in enumerate(self.node_ids)}
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

    def waypoints(self, achieved: np.ndarray, goals: np.ndarray, lookahead: int) -> np.ndarray:
        """For each row, the point ``lookahead`` options along a shortest known path to the goal (else the goal)."""
        result = np.array(goals, dtype=np.float32, copy=True)
        if len(self) == 0:
            return result
        start_ids, goal_ids = self.voxel_ids(achieved), self.voxel_ids(goals)
        for row, (start_voxel, goal_voxel) in enumerate(zip(start_ids, goal_ids, strict=True)):
            start, goal = self._index.get(int(start_voxel)), self._index.get(int(goal_voxel))
            if start is None or goal is None or start == goal:
                continue
            distances = self.distances_to(goal)
            if distances[start] == np.inf:
                continue
            current = start
            for _ in range(lookahead):
                current = min(self._successors[current], key=lambda node: distances[node])
                if current == goal:
                    break
            if current != goal:
                result[row] = self.node_points[current]
        return result
