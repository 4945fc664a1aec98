"""Planning over achieved states: the voxel graph, shortest paths that stitch trajectories, waypoints."""

import numpy as np
import pytest

from sb3_dipper.common.planning import SubgoalGraph
from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.common.trajectories import TrajectoryBuffer
from tests.test_preferences import OBS_SPACE, add_trajectory

SPACE = SubgoalSpace(low=np.zeros(2), high=np.full(2, 10.0), threshold=0.5)


@pytest.fixture
def graph() -> SubgoalGraph:
    buffer = TrajectoryBuffer(capacity=10, max_length=4, observation_space=OBS_SPACE, action_dim=2)
    # Two trajectories that never meet end to end: (0.5,0.5) -> ... -> (3.5,0.5) and (3.5,0.5) -> ... -> (3.5,3.5).
    add_trajectory_from(buffer, (0.5, 0.5), [(1.5, 0.5), (2.5, 0.5), (3.5, 0.5)])
    add_trajectory_from(buffer, (3.5, 0.5), [(3.5, 1.5), (3.5, 2.5), (3.5, 3.5)])
    graph = SubgoalGraph(SPACE, resolution=1.0)
    graph.rebuild(buffer)
    return graph


def add_trajectory_from(buffer: TrajectoryBuffer, start, path) -> None:
    """A trajectory whose first observation is at ``start`` (add_trajectory starts at the origin)."""
    shifted = [(x - start[0], y - start[1]) for x, y in path]
    before = buffer.pos
    add_trajectory(buffer, shifted)
    buffer.observations["achieved_goal"][before, : len(path)] += np.array(start, dtype=np.float32)
    buffer.next_achieved_goals[before, : len(path)] += np.array(start, dtype=np.float32)


def test_voxels_and_edges(graph):
    assert len(graph) == 7
    assert graph.voxel_ids(np.array([[0.5, 0.5], [1.2, 0.1], [9.9, 9.9], [12.0, -3.0]])).tolist() == [0, 10, 99, 90]
    assert len(graph.edges) == 6


def test_shortest_paths_stitch_trajectories(graph):
    goal = graph._index[int(graph.voxel_ids(np.array([[3.5, 3.5]]))[0])]
    start = graph._index[int(graph.voxel_ids(np.array([[0.5, 0.5]]))[0])]
    assert graph.distances_to(goal)[start] == 6.0


def test_waypoints_walk_the_path(graph):
    start, goal = np.array([[0.4, 0.6]]), np.array([[3.5, 3.4]])
    np.testing.assert_allclose(graph.waypoints(start, goal, lookahead=1), [[1.5, 0.5]])
    np.testing.assert_allclose(graph.waypoints(start, goal, lookahead=4), [[3.5, 1.5]])
    # At the last step the waypoint is the goal itself, not its voxel's mean.
    np.testing.assert_allclose(graph.waypoints(np.array([[3.5, 2.5]]), goal, lookahead=3), goal)


def test_unvisited_goal_voxels_plan_to_the_nearest_visited_voxel(graph):
    goal = np.array([[4.6, 3.5]])  # one voxel right of (3.5, 3.5)
    np.testing.assert_allclose(graph.waypoints(np.array([[3.5, 2.5]]), goal, lookahead=1), [[3.5, 3.5]])
    far_goal = np.array([[9.0, 9.0]])
    np.testing.assert_allclose(graph.waypoints(np.array([[3.5, 2.5]]), far_goal, lookahead=1), far_goal)


def test_without_a_known_path_the_goal_is_returned(graph):
    # Edges are directed: nothing leads back from (3.5, 3.5) to the start.
    goal = np.array([[0.5, 0.5]])
    np.testing.assert_allclose(graph.waypoints(np.array([[3.5, 3.5]]), goal, lookahead=1), goal)
    empty = SubgoalGraph(SPACE, resolution=1.0)
    np.testing.assert_allclose(empty.waypoints(np.array([[1.0, 1.0]]), goal, lookahead=1), goal)


def test_resolution_must_be_positive():
    with pytest.raises(ValueError, match="resolution must be positive"):
        SubgoalGraph(SPACE, resolution=0.0)
