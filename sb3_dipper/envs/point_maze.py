"""``PointMazeFourRooms-v0``: gymnasium-robotics' PointMaze in a four-room maze, start and goal in opposite rooms.

The maze is 9 x 9 cells of 1 m (outer walls included): four 3 x 3 rooms joined by four one-cell doorways. An
episode starts at a random cell of the start room (bottom left by default) and the goal is a random cell of the
opposite room (top right), both with gymnasium-robotics' +-0.25 m position noise. The ball needs about 150
primitive steps at full speed along the shortest path, so a 200-step episode leaves little room for wandering: the
gap a hierarchy must close (what DIPPER reaches here: BENCHMARKS.md, the fast maze; every algorithm at a short
budget: the research log of 2026-11-22).

Differences from the upstream env, all chosen so the task is a standard SB3 goal env:

- reward ``-1 / 0`` (sparse, as the Fetch tasks) with a vectorised ``compute_reward``;
- ``info["is_success"]`` (SB3's key), true while the ball is within ``distance_threshold`` (0.45 m) of the goal;
- no termination: an episode is ``max_episode_steps`` (200) long and counts as a success if it ends at the goal,
  as the paper's tasks measure success at the last step.
"""

from __future__ import annotations

import contextlib
import os
from collections import deque
from typing import Any

import numpy as np
from gymnasium_robotics.envs.maze.point_maze import PointMazeEnv

from sb3_dipper.common.subgoals import SubgoalSpace

# Doorways sit at the outer ends of the walls, so heading straight for a goal in the opposite room runs into the
# corner of the central walls: a greedy controller reaches the goal in 2 % of episodes, the scripted expert in all.
FOUR_ROOMS_MAP: list[list[int]] = [
    [1, 1, 1, 1, 1, 1, 1, 1, 1],
    [1, 0, 0, 0, 0, 0, 0, 0, 1],
    [1, 0, 0, 0, 1, 0, 0, 0, 1],
    [1, 0, 0, 0, 1, 0, 0, 0, 1],
    [1, 0, 1, 1, 1, 1, 1, 0, 1],
    [1, 0, 0, 0, 1, 0, 0, 0, 1],
    [1, 0, 0, 0, 1, 0, 0, 0, 1],
    [1, 0, 0, 0, 0, 0, 0, 0, 1],
    [1, 1, 1, 1, 1, 1, 1, 1, 1],
]

ROOMS: dict[str, list[tuple[int, int]]] = {
    "top_left": [(row, col) for row in (1, 2, 3) for col in (1, 2, 3)],
    "top_right": [(row, col) for row in (1, 2, 3) for col in (5, 6, 7)],
    "bottom_left": [(row, col) for row in (5, 6, 7) for col in (1, 2, 3)],
    "bottom_right": [(row, col) for row in (5, 6, 7) for col in (5, 6, 7)],
}

# The interior spans x, y in [-3.5, 3.5]; the ball's centre stays 0.1 m away from every wall.
MAZE_INTERIOR_HALF_WIDTH = 3.5


class PointMazeFourRoomsEnv(PointMazeEnv):
    """Four-room PointMaze with start and goal in chosen rooms.

    :param start_room: room of the start cell (``top_left``, ``top_right``, ``bottom_left``, ``bottom_right``)
    :param goal_room: room of the goal cell
    :param distance_threshold: success radius around the goal, in metres
    :param frame_skip: MuJoCo steps (of 0.01 s) per env step; upstream uses 1, we use 2 so the ball crosses a cell in
        about 10 steps and an episode needs half as many primitive steps for the same path
    :param render_mode: gymnasium render mode (``rgb_array`` works headless with ``MUJOCO_GL=egl``)
    :param kwargs: passed to gymnasium-robotics' ``PointMazeEnv`` (for example ``position_noise_range``)
    """

    def __init__(
        self,
        start_room: str = "bottom_left",
        goal_room: str = "top_right",
        distance_threshold: float = 0.45,
        frame_skip: int = 2,
        render_mode: str | None = None,
        **kwargs: Any,
    ) -> None:
        for name, room in (("start_room", start_room), ("goal_room", goal_room)):
            if room not in ROOMS:
                raise ValueError(f"Unknown {name} {room!r}: choose one of {sorted(ROOMS)}")
        self.start_room = start_room
        self.goal_room = goal_room
        self.distance_threshold = float(distance_threshold)
        super().__init__(
            maze_map=FOUR_ROOMS_MAP,
            render_mode=render_mode,
            reward_type="sparse",
            continuing_task=True,
            reset_target=False,
            **kwargs,
        )
        # Upstream writes the maze's MuJoCo model to a file in the temp folder, reads it once, and never removes it: one
        # file per env made (thousands in a test run).
        with contextlib.suppress(FileNotFoundError):
            os.remove(self.tmp_xml_file_path)
        # Upstream hard-codes one MuJoCo step per env step; the velocity clip still applies before every env step.
        self.point_env.frame_skip = int(frame_skip)
        self.subgoal_space = SubgoalSpace(
            low=np.full(2, -MAZE_INTERIOR_HALF_WIDTH),
            high=np.full(2, MAZE_INTERIOR_HALF_WIDTH),
            threshold=self.distance_threshold,
        )

    def _random_cell_xy(self, room: str) -> np.ndarray:
        cells = ROOMS[room]
        cell = cells[int(self.np_random.integers(len(cells)))]
        return self.maze.cell_rowcol_to_xy(np.array(cell))

    def generate_target_goal(self) -> np.ndarray:
        return self._random_cell_xy(self.goal_room)

    def generate_reset_pos(self) -> np.ndarray:
        return self._random_cell_xy(self.start_room)

    def compute_reward(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any = None) -> np.ndarray:
        distance = np.linalg.norm(np.asarray(achieved_goal) - np.asarray(desired_goal), axis=-1)
        return -(distance > self.distance_threshold).astype(np.float64)

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        obs, _, terminated, truncated, info = super().step(action)
        reward = float(self.compute_reward(obs["achieved_goal"], obs["desired_goal"]))
        info["is_success"] = float(reward == 0.0)
        return obs, reward, terminated, truncated, info


def shortest_cell_path(start: tuple[int, int], goal: tuple[int, int], maze_map: list[list[int]]) -> list[tuple[int, int]]:
    """Breadth-first shortest path over free cells (4-connected), ``start`` and ``goal`` included."""
    parents: dict[tuple[int, int], tuple[int, int] | None] = {start: None}
    queue = deque([start])
    while queue:
        cell = queue.popleft()
        if cell == goal:
            break
        row, col = cell
        for neighbour in ((row - 1, col), (row + 1, col), (row, col - 1), (row, col + 1)):
            if maze_map[neighbour[0]][neighbour[1]] != 1 and neighbour not in parents:
                parents[neighbour] = cell
                queue.append(neighbour)
    if goal not in parents:
        raise ValueError(f"No path from cell {start} to cell {goal}")
    path = [goal]
    while (parent := parents[path[-1]]) is not None:
        path.append(parent)
    return path[::-1]


def reach_action(position: np.ndarray, velocity: np.ndarray, target: np.ndarray) -> np.ndarray:
    """A PD force toward ``target`` that arrives without overshooting much (batched over the leading axis)."""
    return np.clip(2.0 * (target - position) - 0.25 * velocity, -1.0, 1.0).astype(np.float32)


class PointMazeExpert:
    """Scripted expert for the four-room maze: steer to the next cell centre of the shortest cell path, then to the goal.

    :param maze_map: the maze layout (``FOUR_ROOMS_MAP`` by default)
    """

    def __init__(self, maze_map: list[list[int]] | None = None) -> None:
        self.maze_map = FOUR_ROOMS_MAP if maze_map is None else maze_map
        half_rows, half_cols = len(self.maze_map) / 2, len(self.maze_map[0]) / 2
        self._centre = np.array([half_cols, half_rows])

    def _cell(self, xy: np.ndarray) -> tuple[int, int]:
        return int(np.floor(self._centre[1] - xy[1])), int(np.floor(xy[0] + self._centre[0]))

    def _cell_xy(self, cell: tuple[int, int]) -> np.ndarray:
        return np.array([cell[1] + 0.5 - self._centre[0], self._centre[1] - cell[0] - 0.5])

    def reset(self) -> None:
        """Start an episode (the maze expert keeps no state)."""

    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        """The expert action for one (unbatched) maze observation."""
        position, velocity = observation["observation"][:2], observation["observation"][2:4]
        goal = observation["desired_goal"]
        path = shortest_cell_path(self._cell(position), self._cell(goal), self.maze_map)
        target = goal if len(path) <= 2 else self._cell_xy(path[1])
        return reach_action(position, velocity, target)


class PointMazeReachController:
    """Scripted lower level for the maze: steer straight at the subgoal (it does not plan around walls).

    It follows the option layer's lower-level controller protocol, so tests and the RAPS ``reach`` primitive can run
    the option layer without a learned lower level.
    """

    def act(self, low_obs: dict[str, np.ndarray], deterministic: bool) -> np.ndarray:
        observation = low_obs["observation"]
        return reach_action(observation[:, :2], observation[:, 2:4], low_obs["desired_goal"])

    def value(self, low_obs: dict[str, np.ndarray]) -> np.ndarray | None:
        return None
