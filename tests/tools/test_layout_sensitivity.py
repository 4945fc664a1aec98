"""layout_sensitivity.py: how far a higher policy's subgoal moves when only the maze layout changes, and whether it
leads round the walls, on hand-built layouts."""

import numpy as np
import pytest

from sb3_dipper.envs.fetch import MazeGeometry, generate_four_room_layout
from zoo_scripts.research.layout_sensitivity import in_sight, layout_sensitivity, layout_swaps, way_round

MAZE = MazeGeometry()


def observations_of(grids: list[np.ndarray], grips: list[tuple[int, int]], goals: list[tuple[int, int]]) -> dict:
    """Maze observations (original values) of grippers and goals at cell centres, each in its grid."""
    grip_xy = np.array([[*MAZE.cell_xy(cell), MAZE.grip_height] for cell in grips], dtype=np.float32)
    goal_xy = np.array([[*MAZE.cell_xy(cell), MAZE.grip_height] for cell in goals], dtype=np.float32)
    grid_rows = np.stack([grid.ravel() for grid in grids]).astype(np.float32)
    return {"observation": np.concatenate([grip_xy, grid_rows], axis=1), "achieved_goal": grip_xy, "desired_goal": goal_xy}


def layouts(n: int) -> list:
    rng = np.random.default_rng(3)
    return [generate_four_room_layout(rng) for _ in range(n)]


def test_swaps_show_a_start_only_the_layouts_that_leave_its_cells_free():
    drawn = layouts(6)
    observations = observations_of(
        [layout.grid for layout in drawn], [layout.start for layout in drawn], [layout.goal for layout in drawn]
    )
    starts, others = layout_swaps(observations, MAZE, n_layouts=3)
    assert len(starts) > 0 and (starts != others).all()
    for i, j in zip(starts, others, strict=True):
        assert drawn[j].grid[drawn[i].start] == 0 and drawn[j].grid[drawn[i].goal] == 0
    assert max(np.bincount(starts)) <= 3


def test_a_subgoal_blind_to_the_layout_does_not_shift_and_one_that_reads_it_does():
    drawn = layouts(8)
    observations = observations_of(
        [layout.grid for layout in drawn], [layout.start for layout in drawn], [layout.goal for layout in drawn]
    )

    def goal_plus_offset(obs):  # one offset for every layout
        return obs["desired_goal"][:, :3] + np.array([0.05, 0.0, 0.0])

    def by_wall_row(obs):  # moves 1 cm per cell of the horizontal wall's row: a layout changes it
        wall_row = obs["observation"][:, 3:].reshape(-1, MAZE.rows, MAZE.cols)[:, 1:-1, 1].argmax(axis=1)
        return obs["desired_goal"][:, :3] + 0.01 * wall_row[:, None] * np.array([1.0, 0.0, 0.0])

    blind = layout_sensitivity(observations, goal_plus_offset, MAZE, n_layouts=5)
    assert blind["layout_shift"] == 0.0 and blind["goal_offset"] == pytest.approx(0.05, abs=1e-6)
    reading = layout_sensitivity(observations, by_wall_row, MAZE, n_layouts=5)
    assert reading["layout_shift"] > 0.0 and reading["swaps"] == blind["swaps"] > 0


def test_the_way_round_counts_subgoals_in_sight_that_bring_the_gripper_nearer_along_the_free_cells():
    grid = np.zeros((MAZE.rows, MAZE.cols))
    grid[0, :] = grid[-1, :] = grid[:, 0] = grid[:, -1] = 1
    grid[5, 1:10] = 1  # a wall across the room ...
    grid[5, 8] = 0  # ... with a gate at column 8
    observations = observations_of([grid] * 3, [(3, 2)] * 3, [(8, 2)] * 3)
    gate, behind_wall, back = (np.array([*MAZE.cell_xy(cell), MAZE.grip_height]) for cell in ((4, 8), (5, 2), (2, 2)))
    targets = np.stack([gate, behind_wall, back])
    np.testing.assert_array_equal(in_sight(observations, targets, MAZE), [True, False, True])
    goal = observations["desired_goal"].astype(np.float64)
    np.testing.assert_array_equal(in_sight(observations, goal, MAZE), [False] * 3)  # the wall stands between
    # From (3, 2) the goal (8, 2) is 17 cell steps round through the gate (5, 8); from (4, 8) 10; from (2, 2) 18.
    way = way_round(observations, targets[:1].repeat(3, 0), MAZE)
    assert way == {"in_sight": 1.0, "path_gain": pytest.approx(7 * 0.05), "useful": 1.0}
    backwards = way_round(observations, targets[2:].repeat(3, 0), MAZE)
    assert backwards["in_sight"] == 1.0 and backwards["useful"] == 0.0 and backwards["path_gain"] == pytest.approx(-0.05)
    # A subgoal in the outer wall's corner has no way to the goal: no gain, not in the mean.
    corner = np.array([*MAZE.cell_xy((0, 0)), MAZE.grip_height])
    mixed = way_round(observations, np.stack([gate, corner, gate]), MAZE)
    assert mixed["path_gain"] == pytest.approx(7 * 0.05) and mixed["useful"] == pytest.approx(2 / 3)
