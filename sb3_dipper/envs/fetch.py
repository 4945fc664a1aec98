"""Fetch tasks of the DIPPER paper on gymnasium-robotics' MuJoCo Fetch: four-room maze, push, pick-and-place.

``FetchFourRoomMaze-v0`` (:class:`FetchFourRoomMazeEnv`): the paper's maze navigation task. The gripper, closed and
held at table height, moves in the plane through a four-room maze of wall blocks on an 11 x 11 grid of 5 cm cells over
the table (cell ``(row, col)`` at ``x = 1.05 + 0.05 row``, ``y = 0.50 + 0.05 col``: the grid is centred on the table).
Row and column 0 and 10 are the outer walls; one horizontal wall (row ``H_P``) and one vertical wall (column ``W_P``)
split the 9 x 9 interior into four rooms joined by four one-cell gates. The layout is drawn anew at every reset, as in
the paper's appendix; the gripper starts at the centre of a random cell of the room nearest the robot and the goal is
the centre of a random cell of the diagonally opposite room (:func:`generate_four_room_layout`). ``fixed_layout=True``
(the id ``FetchFourRoomMazeFixed-v0``) gives the authors' single layout, start and goal instead (``AUTHORS_LAYOUT``).
Observation: gripper position (3) and the grid flattened (121 cells, 1 = wall), 124 numbers like the authors' code. An
episode is 225 steps (K = T = 15).

``FetchPush-v4`` and ``FetchPickAndPlace-v4`` are gymnasium-robotics' own tasks: this module only declares their
subgoal spaces (the object position). ``FetchPushFixed-v0`` and ``FetchPickAndPlaceFixed-v0`` are the authors' fixed
variants: the object always starts at ``(1.3, 0.65)`` on the table and the goal never moves.

Every task has a deterministic scripted expert in :data:`EXPERTS` (the source of the single demonstration the paper
gives push, pick-and-place and kitchen).
"""

from __future__ import annotations

import os
import tempfile
import xml.etree.ElementTree as ET
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import gymnasium_robotics.envs
import mujoco
import numpy as np
from gymnasium.utils.ezpickle import EzPickle
from gymnasium_robotics.envs.fetch import MujocoFetchEnv
from gymnasium_robotics.envs.fetch.pick_and_place import MujocoFetchPickAndPlaceEnv
from gymnasium_robotics.envs.fetch.push import MujocoFetchPushEnv
from gymnasium_robotics.utils import mujoco_utils

from sb3_dipper.common.subgoals import SubgoalSpace, register_subgoal_space
from sb3_dipper.envs.point_maze import shortest_cell_path

FETCH_ASSETS = Path(gymnasium_robotics.envs.__file__).parent / "assets" / "fetch"

# The Fetch table: a box centred at (1.3, 0.75) with half sizes (0.25, 0.35), its top at z = 0.4.
TABLE_LOW = np.array([1.05, 0.40])
TABLE_HIGH = np.array([1.55, 1.10])
TABLE_TOP_Z = 0.4

# Mocap control of every Fetch task: an action of 1 moves the gripper's target 5 cm.
ACTION_STEP = 0.05
# The gripper points down: the orientation every Fetch task holds its gripper in.
GRIPPER_DOWN_QUAT = np.array([1.0, 0.0, 1.0, 0.0]) / np.sqrt(2.0)


class PlainFloatRewards(gym.Env):
    """Mixin: the reward and ``info["is_success"]`` as Python floats.

    gymnasium-robotics' Fetch tasks return numpy ``float32`` scalars, which SB3's ``check_env`` refuses (learning casts
    them anyway). Put it before the Fetch class in the bases.
    """

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = super().step(action)
        info["is_success"] = float(info["is_success"])
        return obs, float(reward), bool(terminated), bool(truncated), info


# ------------------------------------------------------------------------------------------------------------------
# Maze layouts
# ------------------------------------------------------------------------------------------------------------------

MAZE_ROWS = 11
MAZE_COLS = 11
# Rooms at least two cells wide: the walls stand in rows / columns 3..7, the draws of the authors' randrange(3, 8), a
# subset of the paper's range (1, W - 2).
MIN_ROOM_CELLS = 2

Cell = tuple[int, int]


@dataclass(frozen=True, eq=False)
class FourRoomLayout:
    """A four-room maze on a ``rows x cols`` grid: outer walls, one horizontal and one vertical wall, four gates.

    :param rows: number of grid rows (``H``, along the world x axis)
    :param cols: number of grid columns (``W``, along the world y axis)
    :param wall_row: row of the horizontal wall (``H_P``)
    :param wall_col: column of the vertical wall (``W_P``)
    :param gates: the four gate cells: on the horizontal wall left and right of ``wall_col``, then on the vertical wall
        above and below ``wall_row``
    :param start: start cell of the gripper
    :param goal: goal cell
    """

    rows: int
    cols: int
    wall_row: int
    wall_col: int
    gates: tuple[Cell, Cell, Cell, Cell]
    start: Cell
    goal: Cell
    grid: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        grid = np.zeros((self.rows, self.cols), dtype=np.int8)
        grid[[0, -1], :] = 1
        grid[:, [0, -1]] = 1
        grid[self.wall_row, :] = 1
        grid[:, self.wall_col] = 1
        for gate in self.gates:
            grid[gate] = 0
        grid.flags.writeable = False
        object.__setattr__(self, "grid", grid)

    def room_of(self, cell: Cell) -> tuple[int, int]:
        """``(0 or 1, 0 or 1)``: which side of the horizontal and of the vertical wall ``cell`` lies on."""
        return int(cell[0] > self.wall_row), int(cell[1] > self.wall_col)


def _room_cells(rows: range, cols: range) -> list[Cell]:
    return [(row, col) for row in rows for col in cols]


def generate_four_room_layout(rng: np.random.Generator, rows: int = MAZE_ROWS, cols: int = MAZE_COLS) -> FourRoomLayout:
    """Draw a four-room layout as the paper's appendix describes, then a start and a goal cell in opposite rooms.

    - wall positions ``H_P`` in ``[1 + MIN_ROOM_CELLS, rows - 2 - MIN_ROOM_CELLS]`` and ``W_P`` likewise over the
      columns (``[3, 7]`` on the 11 x 11 grid), inside the paper's ranges ``(1, H - 2)`` and ``(1, W - 2)``;
    - gates on the horizontal wall at a column in ``[1, W_P - 1]`` and one in ``[W_P + 1, W - 2]``, gates on the vertical
      wall at a row in ``[1, H_P - 1]`` and one in ``[H_P + 1, H - 2]`` (the paper's gate ranges, bounds included);
    - start: a uniform cell of the room nearest the robot, on its right (rows ``< H_P``, i.e. low x, and columns
      ``< W_P``, low y), the room of the authors' start cell (1, 3); goal: a uniform cell of the opposite room (rows
      ``> H_P``, columns ``> W_P``), the room of their goal cell (9, 9). The way from one to the other always crosses
      two gates: the task keeps the authors' long-horizon structure while the layout, start and goal vary.

    A breadth-first search checks that the goal is reachable (it always is: four rooms on a cycle of four gates).
    """
    low, high_row, high_col = 1 + MIN_ROOM_CELLS, rows - 2 - MIN_ROOM_CELLS, cols - 2 - MIN_ROOM_CELLS
    if high_row < low or high_col < low:
        raise ValueError(f"A {rows} x {cols} grid is too small for four rooms of {MIN_ROOM_CELLS} cells")
    for _ in range(100):
        wall_row = int(rng.integers(low, high_row + 1))
        wall_col = int(rng.integers(low, high_col + 1))
        gates = (
            (wall_row, int(rng.integers(1, wall_col))),
            (wall_row, int(rng.integers(wall_col + 1, cols - 1))),
            (int(rng.integers(1, wall_row)), wall_col),
            (int(rng.integers(wall_row + 1, rows - 1)), wall_col),
        )
        start_room = _room_cells(range(1, wall_row), range(1, wall_col))
        goal_room = _room_cells(range(wall_row + 1, rows - 1), range(wall_col + 1, cols - 1))
        start = start_room[int(rng.integers(len(start_room)))]
        goal = goal_room[int(rng.integers(len(goal_room)))]
        layout = FourRoomLayout(rows, cols, wall_row, wall_col, gates, start, goal)
        if cells_connected(layout.grid, start, goal):
            return layout
    raise RuntimeError("Could not draw a connected four-room layout")  # unreachable with four gates


def cells_connected(grid: np.ndarray, start: Cell, goal: Cell) -> bool:
    """Whether a 4-connected path of free cells joins ``start`` and ``goal`` (``grid`` must have outer walls)."""
    try:
        shortest_cell_path(start, goal, grid.tolist())
    except ValueError:
        return False
    return True


def _cell_steps_to(grid: np.ndarray, goal: Cell) -> np.ndarray:
    """4-connected steps from every free cell of ``grid`` to ``goal`` over free cells (infinite where none joins)."""
    steps = np.full(grid.shape, np.inf)
    steps[goal] = 0.0
    queue = deque([goal])
    while queue:
        row, col = queue.popleft()
        for neighbour in ((row - 1, col), (row + 1, col), (row, col - 1), (row, col + 1)):
            inside = 0 <= neighbour[0] < grid.shape[0] and 0 <= neighbour[1] < grid.shape[1]
            if inside and grid[neighbour] != 1 and steps[neighbour] == np.inf:
                steps[neighbour] = steps[row, col] + 1.0
                queue.append(neighbour)
    return steps


# The authors' single layout (their env index 0): their generator seeds Python's ``random`` with 0 and draws the wall
# row, the wall column and the four gates with ``randrange``. Replaying those draws (Python's Mersenne Twister and
# integer ``randrange`` are unchanged since Python 3.2, so 3.11 gives what their 3.6 gave) yields wall row 6, wall
# column 6 and gates (6, 1), (6, 8), (5, 6), (8, 6); their start cell is (1, 3) and their goal cell (9, 9). We hard-code
# the result rather than the RNG: it is their layout as far as their published generator reads, which we could not
# run. Their grid has no outer walls (a tray around the table bounds it) and 0.049 m rows; ours has outer walls and
# 0.05 m square cells, so the rooms are the same cells and the gripper positions differ by at most 2 cm.
AUTHORS_LAYOUT = FourRoomLayout(
    rows=MAZE_ROWS,
    cols=MAZE_COLS,
    wall_row=6,
    wall_col=6,
    gates=((6, 1), (6, 8), (5, 6), (8, 6)),
    start=(1, 3),
    goal=(9, 9),
)


@dataclass(frozen=True)
class MazeGeometry:
    """Where the maze grid sits: cell ``(row, col)`` is centred at ``origin + cell_size * (row, col)``.

    :param rows: number of grid rows (along x)
    :param cols: number of grid columns (along y)
    :param cell_size: side of a square cell, in metres
    :param origin: world ``(x, y)`` of the centre of cell ``(0, 0)``
    :param grip_height: height of the gripper's grip site, held fixed
    """

    rows: int = MAZE_ROWS
    cols: int = MAZE_COLS
    cell_size: float = 0.05
    origin: tuple[float, float] = (1.05, 0.50)
    grip_height: float = 0.425

    def cell_xy(self, cell: Cell) -> np.ndarray:
        return np.asarray(self.origin) + self.cell_size * np.asarray(cell, dtype=np.float64)

    def cell_of(self, xy: np.ndarray) -> Cell:
        row, col = np.rint((np.asarray(xy[:2]) - np.asarray(self.origin)) / self.cell_size).astype(int)
        return int(np.clip(row, 0, self.rows - 1)), int(np.clip(col, 0, self.cols - 1))

    def path_distances(self, observations: np.ndarray, points: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """How far each point lies from its goal along the maze's free cells, in metres, ``(N,)``: the cell size times
        the number of 4-connected steps from the point's cell to the goal's over free cells of the layout its
        observation holds, or the straight distance within the goal's cell. This is the progress an oracle that knows
        the walls compares, where the straight distance would prefer a gripper pressed against the wall nearest the
        goal. A point rounded into a wall cell (the gripper touching a block) counts from its nearest free neighbour.

        :param observations: maze observations ``(N, 3 + rows * cols)`` (gripper position, then the grid, 1 = wall)
        :param points: ``(N, >= 2)`` positions (achieved goals)
        :param goals: ``(N, >= 2)`` goal positions
        """
        observations, points, goals = np.atleast_2d(observations), np.atleast_2d(points), np.atleast_2d(goals)
        if observations.shape[-1] != 3 + self.rows * self.cols:
            raise ValueError(
                f"observations must hold the gripper position and a {self.rows} x {self.cols} grid "
                f"({3 + self.rows * self.cols} numbers per row), got shape {observations.shape}"
            )
        distances = np.empty(len(points))
        fields: dict[tuple[bytes, Cell], np.ndarray] = {}
        for index, (observation, point, goal) in enumerate(zip(observations, points, goals, strict=True)):
            grid = np.rint(observation[3:]).astype(np.int8).reshape(self.rows, self.cols)
            goal_cell, cell = self.cell_of(goal), self.cell_of(point)
            key = (grid.tobytes(), goal_cell)
            if key not in fields:
                fields[key] = _cell_steps_to(grid, goal_cell)
            steps = fields[key]
            if grid[cell] == 1:
                neighbours = [(cell[0] + dr, cell[1] + dc) for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1))]
                inside = [n for n in neighbours if 0 <= n[0] < self.rows and 0 <= n[1] < self.cols]
                distances[index] = self.cell_size * (1 + min(steps[n] for n in inside))
            elif cell == goal_cell:
                distances[index] = float(np.linalg.norm(np.asarray(point[:2]) - np.asarray(goal[:2])))
            else:
                distances[index] = self.cell_size * steps[cell]
        return distances

    @property
    def interior_low(self) -> np.ndarray:
        """Lower ``(x, y)`` corner of the free interior (the inner faces of the outer walls)."""
        return self.cell_xy((1, 1)) - 0.5 * self.cell_size

    @property
    def interior_high(self) -> np.ndarray:
        return self.cell_xy((self.rows - 2, self.cols - 2)) + 0.5 * self.cell_size


# A wall block fills its cell but for 2 mm gaps (no slot a finger could catch in) and stands 5 cm tall on the table,
# so the closed fingers (2.7 x 3.0 cm, from 1.8 cm below the grip site up) hit it at the maze's grip height.
WALL_HALF_SIZE = (0.024, 0.024, 0.025)
# Unused blocks wait under the floor, where they touch nothing (MuJoCo never collides two static bodies).
PARKED_BLOCK_POS = (1.3, 0.75, -0.5)

MAZE_CAMERA_CONFIG = {
    "distance": 1.2,
    "azimuth": 180.0,
    "elevation": -65.0,
    "lookat": np.array([1.3, 0.75, 0.4]),
}

# Settling the arm at a new start cell: 20-substep chunks until the grip site rests (moves under 0.1 mm in a chunk).
# It then sits within 3 mm of its target (the soft weld lags most in the row nearest the robot).
SETTLE_MAX_CHUNKS = 50
SETTLE_REST_MOTION = 1e-4


def _maze_model_xml(n_blocks: int) -> str:
    """gymnasium-robotics' reach model plus ``n_blocks`` static wall blocks, with absolute asset paths."""
    tree = ET.parse(FETCH_ASSETS / "reach.xml")
    root = tree.getroot()
    compiler = root.find("compiler")
    if compiler is not None:
        for attribute in ("meshdir", "texturedir"):
            compiler.set(attribute, str((FETCH_ASSETS / compiler.get(attribute, ".")).resolve()))
    for include in root.iter("include"):
        include.set("file", str(FETCH_ASSETS / include.get("file", "")))
    asset = ET.SubElement(root, "asset")
    ET.SubElement(asset, "material", name="maze_wall_mat", specular="0", shininess="0.5", rgba="0.85 0.6 0.2 1")
    worldbody = root.find("worldbody")
    assert worldbody is not None, "reach.xml has no worldbody"
    size = " ".join(str(value) for value in WALL_HALF_SIZE)
    position = " ".join(str(value) for value in PARKED_BLOCK_POS)
    for index in range(n_blocks):
        body = ET.SubElement(worldbody, "body", name=f"maze_wall{index}", pos=position)
        ET.SubElement(body, "geom", name=f"maze_wall{index}", type="box", size=size, material="maze_wall_mat", condim="3")
    return ET.tostring(root, encoding="unicode")


class FetchFourRoomMazeEnv(PlainFloatRewards, MujocoFetchEnv, EzPickle):
    """The paper's Fetch maze: move the closed gripper, at table height, through a random four-room maze to the goal.

    Every layout has the same number of wall cells (outer walls, two crossing walls, four gates), so the model holds
    exactly that many static block bodies and each reset moves them (``model.body_pos``) onto the new layout's wall
    cells; the code parks any unused block under the floor, which only a different grid size would need. The gripper
    starts at the centre of its start cell: the arm is settled there once per cell (with the walls parked) and the
    settled joint state is cached, so a reset costs one ``mj_forward``.

    Actions: ``a[:2]`` move the gripper target by up to 5 cm in x and y (as every Fetch task), ``a[2]`` and ``a[3]`` are
    ignored (the target's height is fixed and the gripper is blocked closed). Reward ``-1 / 0`` (0 within
    ``distance_threshold`` of the goal), ``info["is_success"]``, no termination.

    :param fixed_layout: always the authors' layout, start cell (1, 3) and goal cell (9, 9) (see ``AUTHORS_LAYOUT``)
        instead of a new random layout, start and goal at every reset
    :param reward_type: ``sparse`` (``-1 / 0``) or ``dense`` (minus the distance)
    :param distance_threshold: success radius around the goal, in metres
    :param kwargs: passed to gymnasium-robotics' ``MujocoFetchEnv`` (``render_mode``, ``width``, ``height``)
    """

    def __init__(
        self,
        fixed_layout: bool = False,
        reward_type: str = "sparse",
        distance_threshold: float = 0.05,
        **kwargs: Any,
    ) -> None:
        self.fixed_layout = bool(fixed_layout)
        self.maze = MazeGeometry()
        self.layout = AUTHORS_LAYOUT
        self._n_blocks = int(AUTHORS_LAYOUT.grid.sum())
        self._start_states: dict[Cell, tuple[np.ndarray, np.ndarray]] = {}
        # Gripper-link body minus grip site: the mocap drives the body, we place the grip site.
        self._grip_to_mocap = np.array([0.0, 0.0, 0.02])
        kwargs.setdefault("default_camera_config", MAZE_CAMERA_CONFIG)
        descriptor, model_path = tempfile.mkstemp(prefix="fetch_four_room_maze_", suffix=".xml")
        try:
            with os.fdopen(descriptor, "w") as model_file:
                model_file.write(_maze_model_xml(self._n_blocks))
            MujocoFetchEnv.__init__(
                self,
                model_path=model_path,
                has_object=False,
                block_gripper=True,
                n_substeps=20,
                gripper_extra_height=0.0,
                target_in_the_air=False,
                target_offset=0.0,
                obj_range=0.0,
                target_range=0.0,
                distance_threshold=distance_threshold,
                initial_qpos={"robot0:slide0": 0.4049, "robot0:slide1": 0.48, "robot0:slide2": 0.0},
                reward_type=reward_type,
                **kwargs,
            )
        finally:
            # The model is compiled: the file is no longer needed.
            os.remove(model_path)
        EzPickle.__init__(
            self, fixed_layout=fixed_layout, reward_type=reward_type, distance_threshold=distance_threshold, **kwargs
        )
        self._block_ids = np.array(
            [mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, f"maze_wall{index}") for index in range(self._n_blocks)]
        )
        # The higher level controls x and y only: the env holds the gripper's height, so a z subgoal would be a
        # coordinate no lower level can change (indices=(0, 1) projects the achieved goal onto x, y).
        self.subgoal_space = SubgoalSpace(
            low=self.maze.interior_low, high=self.maze.interior_high, threshold=0.05, indices=(0, 1)
        )

    # --- simulation ------------------------------------------------------------------------------------------------

    def _grip_position(self) -> np.ndarray:
        return mujoco_utils.get_site_xpos(self.model, self.data, "robot0:grip").copy()

    def _settle_gripper(self, grip_target: np.ndarray) -> None:
        """Hold the mocap at ``grip_target`` until the grip site stops there."""
        self.data.mocap_pos[0] = grip_target + self._grip_to_mocap
        self.data.mocap_quat[0] = GRIPPER_DOWN_QUAT
        previous = self._grip_position()
        for _ in range(SETTLE_MAX_CHUNKS):
            mujoco.mj_step(self.model, self.data, nstep=self.n_substeps)
            self._step_callback()
            position = self._grip_position()
            if np.linalg.norm(position - previous) < SETTLE_REST_MOTION:
                break
            previous = position

    def _grip_target(self, cell: Cell) -> np.ndarray:
        return np.append(self.maze.cell_xy(cell), self.maze.grip_height)

    def _env_setup(self, initial_qpos: dict[str, Any]) -> None:
        for name, value in initial_qpos.items():
            mujoco_utils.set_joint_qpos(self.model, self.data, name, value)
        mujoco_utils.reset_mocap_welds(self.model, self.data)
        mujoco.mj_forward(self.model, self.data)
        home = self._grip_target(AUTHORS_LAYOUT.start)
        self._settle_gripper(home)
        # Measure the body-to-grip offset in the final orientation, then settle again with the exact offset.
        body_id = self._model_names.body_name2id["robot0:gripper_link"]
        self._grip_to_mocap = self.data.xpos[body_id] - self._grip_position()
        self._settle_gripper(home)
        self.initial_gripper_xpos = self._grip_position()
        # Goals sit at the height the gripper actually holds (a fraction of a millimetre under its target).
        self.goal_height = float(self.initial_gripper_xpos[2])

    def _start_state(self, cell: Cell) -> tuple[np.ndarray, np.ndarray]:
        """Joint positions and velocities with the gripper settled at ``cell``'s centre (computed once per cell)."""
        if cell not in self._start_states:
            mujoco.mj_resetData(self.model, self.data)
            self.data.qpos[:] = self.initial_qpos
            self.data.qvel[:] = self.initial_qvel
            self._place_walls(np.zeros((self.maze.rows, self.maze.cols), dtype=np.int8))
            mujoco.mj_forward(self.model, self.data)
            self._settle_gripper(self._grip_target(cell))
            self._start_states[cell] = (self.data.qpos.copy(), self.data.qvel.copy())
        return self._start_states[cell]

    def _place_walls(self, grid: np.ndarray) -> None:
        """Put one block on every wall cell of ``grid`` and park the others."""
        wall_cells = np.argwhere(grid == 1)
        if len(wall_cells) > self._n_blocks:
            raise ValueError(f"The layout has {len(wall_cells)} wall cells but the model only {self._n_blocks} blocks")
        positions = np.tile(np.asarray(PARKED_BLOCK_POS), (self._n_blocks, 1))
        positions[: len(wall_cells), :2] = np.asarray(self.maze.origin) + self.maze.cell_size * wall_cells
        positions[: len(wall_cells), 2] = TABLE_TOP_Z + WALL_HALF_SIZE[2]
        self.model.body_pos[self._block_ids] = positions

    def _reset_sim(self) -> bool:
        self.layout = AUTHORS_LAYOUT if self.fixed_layout else generate_four_room_layout(self.np_random)
        qpos, qvel = self._start_state(self.layout.start)
        mujoco.mj_resetData(self.model, self.data)
        self.data.time = self.initial_time
        self.data.qpos[:] = qpos
        self.data.qvel[:] = qvel
        self._place_walls(self.layout.grid)
        mujoco.mj_forward(self.model, self.data)
        mujoco_utils.reset_mocap2body_xpos(self.model, self.data)
        return True

    def _sample_goal(self) -> np.ndarray:
        return np.append(self.maze.cell_xy(self.layout.goal), self.goal_height)

    def _set_action(self, action: np.ndarray) -> None:
        # Planar control: the mocap target follows the gripper in x, y (as upstream) but keeps its height.
        mujoco_utils.reset_mocap2body_xpos(self.model, self.data)
        self.data.mocap_pos[0, :2] += np.asarray(action[:2], dtype=np.float64) * ACTION_STEP
        self.data.mocap_pos[0, 2] = self.maze.grip_height + self._grip_to_mocap[2]
        self.data.mocap_quat[0] = GRIPPER_DOWN_QUAT

    def _get_obs(self) -> dict[str, np.ndarray]:
        grip_position = self._grip_position()
        return {
            "observation": np.concatenate([grip_position, self.layout.grid.ravel().astype(np.float64)]),
            "achieved_goal": grip_position.copy(),
            "desired_goal": np.asarray(self.goal, dtype=np.float64).copy(),
        }


# ------------------------------------------------------------------------------------------------------------------
# Push and pick-and-place
# ------------------------------------------------------------------------------------------------------------------

# Object position bounds: x, y over the table; the resting object's centre is 0.425 high, pick-and-place goals reach
# 0.45 m above that.
OBJECT_REST_Z = 0.425


def push_subgoal_space(env: gym.Env | None = None) -> SubgoalSpace:
    """The object position over the table, at table height."""
    return SubgoalSpace(
        low=np.array([*TABLE_LOW, OBJECT_REST_Z - 0.025]),
        high=np.array([*TABLE_HIGH, OBJECT_REST_Z + 0.025]),
        threshold=0.05,
    )


def pick_and_place_subgoal_space(env: gym.Env | None = None) -> SubgoalSpace:
    """The object position over the table and in the air above it, up to the highest goal."""
    return SubgoalSpace(
        low=np.array([*TABLE_LOW, OBJECT_REST_Z - 0.025]),
        high=np.array([*TABLE_HIGH, OBJECT_REST_Z + 0.475]),
        threshold=0.05,
    )


# The authors' fixed tasks: the object always starts here, 11 cm from the gripper's start (1.34, 0.75).
FIXED_OBJECT_XY = np.array([1.3, 0.65])
# Their pick-and-place goal, 23.5 cm above the resting object.
FIXED_PICK_AND_PLACE_GOAL = np.array([1.45, 0.80, 0.66])
# Their push goal cannot be recovered (their push env is broken as released); we push to the pick goal's spot on the
# table, 21 cm diagonally from the object. The gripper starts on the goal's side of the object, so it has to go around
# the object before pushing.
FIXED_PUSH_GOAL_XY = np.array([1.45, 0.80])


def _place_object(env: MujocoFetchEnv, xy: np.ndarray) -> None:
    object_qpos = mujoco_utils.get_joint_qpos(env.model, env.data, "object0:joint").copy()
    object_qpos[:2] = xy
    mujoco_utils.set_joint_qpos(env.model, env.data, "object0:joint", object_qpos)
    mujoco.mj_forward(env.model, env.data)


class FetchPushFixedEnv(PlainFloatRewards, MujocoFetchPushEnv):
    """``FetchPush-v4`` with the authors' fixed object start ``(1.3, 0.65)`` and a fixed goal ``(1.45, 0.80)`` on the table.

    :param reward_type: ``sparse`` or ``dense``
    :param kwargs: passed to gymnasium-robotics' ``MujocoFetchPushEnv``
    """

    def __init__(self, reward_type: str = "sparse", **kwargs: Any) -> None:
        super().__init__(reward_type=reward_type, **kwargs)
        self.subgoal_space = push_subgoal_space(self)

    def _reset_sim(self) -> bool:
        super()._reset_sim()  # draws a random object position, replaced here
        _place_object(self, FIXED_OBJECT_XY)
        return True

    def _sample_goal(self) -> np.ndarray:
        return np.array([*FIXED_PUSH_GOAL_XY, self.height_offset])


class FetchPickAndPlaceFixedEnv(PlainFloatRewards, MujocoFetchPickAndPlaceEnv):
    """``FetchPickAndPlace-v4`` with the authors' fixed object start ``(1.3, 0.65)`` and goal ``(1.45, 0.8, 0.66)``.

    :param reward_type: ``sparse`` or ``dense``
    :param kwargs: passed to gymnasium-robotics' ``MujocoFetchPickAndPlaceEnv``
    """

    def __init__(self, reward_type: str = "sparse", **kwargs: Any) -> None:
        super().__init__(reward_type=reward_type, **kwargs)
        self.subgoal_space = pick_and_place_subgoal_space(self)

    def _reset_sim(self) -> bool:
        super()._reset_sim()  # draws a random object position, replaced here
        _place_object(self, FIXED_OBJECT_XY)
        return True

    def _sample_goal(self) -> np.ndarray:
        return FIXED_PICK_AND_PLACE_GOAL.copy()


# ------------------------------------------------------------------------------------------------------------------
# Scripted experts
# ------------------------------------------------------------------------------------------------------------------


def _toward(position: np.ndarray, target: np.ndarray, gain: float = 1.0) -> np.ndarray:
    """Mocap action that moves ``position`` to ``target`` (``gain = 1``: the whole way in one step, if within 5 cm)."""
    return np.clip(gain * (np.asarray(target) - np.asarray(position)) / ACTION_STEP, -1.0, 1.0)


class FetchMazeExpert:
    """Scripted maze expert: plan a shortest cell path with breadth-first search, steer through its corners.

    The path is straightened to its corner cells, and the gripper goes to each corner's centre before turning, so it
    moves along the corridors' centre lines and never clips a wall's corner. It plans again whenever the observed
    layout or goal changes, so it also works without ``reset()``.

    :param env: the maze env (its geometry is read from ``env.unwrapped.maze``)
    """

    # Distance at which a corner counts as reached.
    corner_tolerance = 0.008

    def __init__(self, env: gym.Env) -> None:
        self.maze: MazeGeometry = env.unwrapped.maze  # type: ignore[attr-defined]
        self.reset()

    def reset(self) -> None:
        """Forget the plan."""
        self._plan_key: bytes | None = None
        self._waypoints: list[np.ndarray] = []
        self._index = 0

    def _plan(self, position: np.ndarray, goal: np.ndarray, grid: np.ndarray) -> None:
        path = shortest_cell_path(self.maze.cell_of(position), self.maze.cell_of(goal), grid.astype(int).tolist())
        corners = [
            path[index]
            for index in range(1, len(path) - 1)
            if (path[index][0] - path[index - 1][0], path[index][1] - path[index - 1][1])
            != (path[index + 1][0] - path[index][0], path[index + 1][1] - path[index][1])
        ]
        self._waypoints = [self.maze.cell_xy(corner) for corner in corners] + [np.asarray(goal[:2], dtype=np.float64)]
        self._index = 0

    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        """The expert action for one (unbatched) maze observation."""
        position = np.asarray(observation["observation"][:3])
        grid = np.asarray(observation["observation"][3:]).reshape(self.maze.rows, self.maze.cols)
        goal = np.asarray(observation["desired_goal"])
        key = grid.astype(np.int8).tobytes() + goal.tobytes()
        if key != self._plan_key:
            self._plan(position, goal, grid)
            self._plan_key = key
        while (
            self._index < len(self._waypoints) - 1
            and np.linalg.norm(self._waypoints[self._index] - position[:2]) < self.corner_tolerance
        ):
            self._index += 1
        action = np.zeros(4, dtype=np.float32)
        action[:2] = _toward(position[:2], self._waypoints[self._index])
        return action


class FetchPushExpert:
    """Scripted push expert: get behind the object on the goal line (passing above it), then push it to the goal.

    Every step it recomputes the push direction from the object to the goal. While the gripper sits behind the object
    on that line it pushes, aiming at the spot from which the object would have moved ``step`` towards the goal, with
    ``step`` half the remaining distance (at most ``max_push_step``): the object slows down near the goal instead of
    sliding past it (a block shoved at the gripper's top speed slides 3-4 cm). When the object drifts off the line the
    gripper lifts above the object and goes behind it again.

    :param env: the push env (not used: everything comes from the observation)
    """

    # Gripper-centre to object-centre distance when touching: 2.5 cm half block plus 1.4-1.5 cm of finger.
    contact = 0.04
    # Where the gripper lines up before pushing, 1 cm short of touching the object.
    pre_push = 0.05
    max_push_step = 0.03
    # Height of the grip site while pushing (fingers 1 cm above the table) and while passing above the object.
    push_height = OBJECT_REST_Z - 0.005
    clear_height = OBJECT_REST_Z + 0.07
    # Stop pushing when the object is this close to the goal (the success radius is 5 cm).
    done_radius = 0.015

    def __init__(self, env: gym.Env) -> None:
        self.reset()

    def reset(self) -> None:
        """Start an episode in the approach phase."""
        self._pushing = False

    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        """The expert action for one (unbatched) push observation."""
        grip = np.asarray(observation["observation"][:3])
        obj = np.asarray(observation["achieved_goal"])
        goal = np.asarray(observation["desired_goal"])
        to_goal = goal[:2] - obj[:2]
        distance = float(np.linalg.norm(to_goal))
        action = np.zeros(4, dtype=np.float32)
        if distance < self.done_radius:
            return action
        direction = to_goal / distance
        relative = grip[:2] - obj[:2]
        along = float(relative @ direction)
        lateral = float(np.linalg.norm(relative - along * direction))
        # Keep pushing while the gripper stays behind the object; close to the goal the direction swings with every
        # millimetre the object drifts sideways, so the lateral tolerance widens there.
        tolerance = 0.02 if distance > 0.06 else 0.03
        self._pushing = self._pushing and along < -0.5 * self.contact and lateral < tolerance
        if self._pushing:
            step = min(self.max_push_step, 0.5 * distance)
            target = np.append(obj[:2] + direction * (step - self.contact), self.push_height)
        else:
            behind = obj[:2] - self.pre_push * direction
            if np.linalg.norm(behind - grip[:2]) > 0.01:
                # Travel above the object; lift first when low next to it.
                target = np.append(behind, self.clear_height)
                if grip[2] < self.clear_height - 0.03 and np.linalg.norm(relative) < 0.08:
                    target[:2] = grip[:2]
            else:
                target = np.append(behind, self.push_height)
                self._pushing = abs(grip[2] - self.push_height) < 0.01
        action[:3] = _toward(grip, target)
        return action


class FetchPickAndPlaceExpert:
    """Scripted pick-and-place expert: open above the object, descend, close, then carry the object to the goal.

    The carry aims the object (not the gripper) at the goal, first at least 5 cm above the table so it is not dragged;
    if the object slips out of the hand the expert starts over.

    :param env: the pick-and-place env (not used: everything comes from the observation)
    """

    approach_height = 0.06
    grasp_steps = 3
    lift_height = OBJECT_REST_Z + 0.05

    def __init__(self, env: gym.Env) -> None:
        self.reset()

    def reset(self) -> None:
        """Start an episode in the reaching phase."""
        self._phase = "reach"
        self._closing_steps = 0

    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        """The expert action for one (unbatched) pick-and-place observation."""
        grip = np.asarray(observation["observation"][:3])
        obj = np.asarray(observation["achieved_goal"])
        goal = np.asarray(observation["desired_goal"])
        action = np.zeros(4, dtype=np.float32)
        if self._phase == "carry" and np.linalg.norm(obj - grip) > 0.03:
            self._phase = "reach"
        if self._phase == "reach":
            action[3] = 1.0
            if np.linalg.norm(obj[:2] - grip[:2]) > 0.01:
                target = obj + np.array([0.0, 0.0, self.approach_height])
                if grip[2] < obj[2] + 0.5 * self.approach_height:
                    target[:2] = grip[:2]  # lift before moving across: open fingers would knock the object
            else:
                target = obj
                if np.linalg.norm(obj - grip) < 0.01:
                    self._phase, self._closing_steps = "grasp", 0
            action[:3] = _toward(grip, target)
        elif self._phase == "grasp":
            action[3] = -1.0
            action[:3] = _toward(grip, obj)
            self._closing_steps += 1
            if self._closing_steps >= self.grasp_steps:
                self._phase = "carry"
        else:
            action[3] = -1.0
            target = goal.copy()
            if np.linalg.norm(goal[:2] - obj[:2]) > 0.02:
                target[2] = max(goal[2], self.lift_height)
            action[:3] = _toward(obj, target)
        return action


# ------------------------------------------------------------------------------------------------------------------
# Registration
# ------------------------------------------------------------------------------------------------------------------

EXPERTS: dict[str, Any] = {
    "FetchFourRoomMaze-v0": FetchMazeExpert,
    "FetchFourRoomMazeFixed-v0": FetchMazeExpert,
    "FetchPush-v4": FetchPushExpert,
    "FetchPickAndPlace-v4": FetchPickAndPlaceExpert,
    "FetchPushFixed-v0": FetchPushExpert,
    "FetchPickAndPlaceFixed-v0": FetchPickAndPlaceExpert,
}

_OUR_ENVS: dict[str, tuple[str, int, dict[str, Any]]] = {
    # K x T = 15 x 15 primitive steps; a new layout every episode, or the authors' single layout.
    "FetchFourRoomMaze-v0": ("sb3_dipper.envs.fetch:FetchFourRoomMazeEnv", 225, {}),
    "FetchFourRoomMazeFixed-v0": ("sb3_dipper.envs.fetch:FetchFourRoomMazeEnv", 225, {"fixed_layout": True}),
    # Upstream's 50 steps, as for the v4 ids; the zoo entries run the paper's K x T = 7 x 7 = 49 through env_kwargs.
    "FetchPushFixed-v0": ("sb3_dipper.envs.fetch:FetchPushFixedEnv", 50, {}),
    "FetchPickAndPlaceFixed-v0": ("sb3_dipper.envs.fetch:FetchPickAndPlaceFixedEnv", 50, {}),
}


def register_fetch_envs() -> None:
    """Register the Fetch env ids and the subgoal spaces of gymnasium-robotics' push and pick-and-place (idempotent)."""
    for env_id, (entry_point, max_episode_steps, kwargs) in _OUR_ENVS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point, max_episode_steps=max_episode_steps, kwargs=kwargs)
    register_subgoal_space("FetchPush-v4", push_subgoal_space)
    register_subgoal_space("FetchPickAndPlace-v4", pick_and_place_subgoal_space)
