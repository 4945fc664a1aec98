"""Pictures of a queued pair for the labelling page: one PNG per trajectory, both toward the pair's goal.

Which of these pictures an env gets is decided by :func:`~sb3_dipper.labelling.drawable.drawing_of`; other envs get none:

- Mazes (an env with a gymnasium-robotics ``maze``): a top-down view of the maze (walls from its maze map) with the
  trajectory's start, the subgoals it proposed (crosses, if the queue records a subgoal space), the states it reached
  after each option (dots joined in order) and the goal (a star inside its success radius).
- MuJoCo robotics (Fetch, Franka Kitchen): a strip of frames rendered headless (``MUJOCO_GL=egl``): the state at the
  start, then the states reached after evenly spaced options (all options if there are few). Each frame puts the
  stored achieved goal back into the simulation, which is all of the state a pair stores: Fetch's object position
  (the gripper position for FetchReach, moved there by its mocap), or Kitchen's task joints; the rest of the scene
  (the arm, for Fetch object tasks) stays where the env's reset left it. The goal is Fetch's red target sphere in
  every frame; for Kitchen, the strip's last frame shows the goal state.
"""

from __future__ import annotations

import io
import math
from typing import Any

import gymnasium as gym
import numpy as np
from matplotlib import patheffects
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Rectangle

from sb3_dipper.common.preferences import TrajectoryPairs
from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.labelling.drawable import KITCHEN, MAZE, drawing_of, make_render_env

SIDES = ("left", "right")
# At most this many frames per strip (the start, then evenly spaced reached states).
MAX_FRAMES = 6
# Frames per row: a trajectory's picture stays about as wide as a maze's, so two fit side by side on the page.
FRAMES_PER_ROW = 3
COLOURS = {"left": "tab:blue", "right": "tab:orange"}
# Pictures are drawn at the size the page shows them (4 inches, 400 px: a side of the pair in a 1280-px window beside
# the how-to), so their text is not scaled down: titles, legends and subgoal numbers in points at this resolution.
DPI = 100
TITLE_SIZE = 13
LABEL_SIZE = 11


class PairRenderer:
    """Draws the pairs of one label queue, from its ``queue.json`` (env id and kwargs, subgoal space).

    :param info: the queue's ``queue.json`` content
    """

    def __init__(self, info: dict[str, Any]) -> None:
        env_id = info.get("env_id")
        if not env_id:
            raise ValueError("The label queue does not say which env its pairs come from (queue.json has no env_id)")
        self.env_id = str(env_id)
        self.env_kwargs = dict(info.get("env_kwargs") or {})
        space = info.get("subgoal_space")
        self.subgoal_space = None
        if space is not None:
            indices = None if space.get("indices") is None else tuple(space["indices"])
            self.subgoal_space = SubgoalSpace(np.array(space["low"]), np.array(space["high"]), space["threshold"], indices)
        self._env: gym.Env | None = None

    @property
    def env(self) -> gym.Env:
        if self._env is None:
            self._env = make_render_env(self.env_id, self.env_kwargs)
        return self._env

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
            self._env = None

    def render(self, pair: TrajectoryPairs, side: str) -> bytes:
        """The PNG of one trajectory (``"left"``: the first, ``"right"``: the second) of a batch of one pair."""
        index = SIDES.index(side)
        drawing = drawing_of(self.env.unwrapped)
        if drawing == MAZE:
            figure = self._maze_figure(pair, index, side)
        else:
            figure = self._frame_strip_figure(pair, index, side, drawing)
        buffer = io.BytesIO()
        figure.savefig(buffer, format="png", dpi=DPI)
        return buffer.getvalue()

    # ---------------------------------------------------------------------------------------------------- mazes

    def _maze_figure(self, pair: TrajectoryPairs, index: int, side: str) -> Figure:
        maze = self.env.unwrapped.maze  # type: ignore[attr-defined]
        scale = maze.maze_size_scaling
        # matplotlib's object API, not pyplot: no global state, so no backend to choose and nothing to close.
        figure = Figure(figsize=(4.0, 4.9))
        axes = figure.subplots()
        for row, cells in enumerate(maze.maze_map):
            for col, cell in enumerate(cells):
                if cell == 1:
                    x = col * scale - maze.x_map_center
                    y = maze.y_map_center - (row + 1) * scale
                    axes.add_patch(Rectangle((x, y), scale, scale, color="0.35"))
        mask = pair.mask[index, 0]
        start = pair.observations["achieved_goal"][index, 0, 0, :2]
        reached = pair.next_achieved_goals[index, 0, mask, :2]
        goal = pair.observations["desired_goal"][index, 0, 0, :2]
        colour = COLOURS[side]
        path = np.vstack([start, reached])
        axes.plot(path[:, 0], path[:, 1], "-o", color=colour, markersize=6, linewidth=2, label="an option ended here")
        axes.plot(*start, "s", color="black", markersize=10, label="start", zorder=5)  # above a goal drawn over it
        if self.subgoal_space is not None:
            subgoals = self.subgoal_space.to_world(pair.actions[index, 0, mask])[:, :2]
            axes.plot(subgoals[:, 0], subgoals[:, 1], "x", color="tab:red", markersize=9, mew=2.5, label="subgoal, in order")
            # White-edged numbers: readable over the walls and the paths alike.
            outline = [patheffects.withStroke(linewidth=3, foreground="white")]
            for number, (subgoal, point) in enumerate(zip(subgoals, reached, strict=True), start=1):
                axes.annotate(
                    str(number),
                    subgoal,
                    fontsize=LABEL_SIZE + 1,
                    fontweight="bold",
                    color="tab:red",
                    xytext=(5, 4),
                    textcoords="offset points",
                    path_effects=outline,
                )
                axes.plot([subgoal[0], point[0]], [subgoal[1], point[1]], ":", color="tab:red", linewidth=1.2)
        threshold = getattr(self.env.unwrapped, "distance_threshold", 0.45)
        axes.add_patch(Circle(tuple(goal), threshold, color="gold", alpha=0.35))
        axes.plot(*goal, "*", color="goldenrod", markersize=20, label="goal")
        half_width = maze.x_map_center, maze.y_map_center
        axes.set_xlim(-half_width[0], half_width[0])
        axes.set_ylim(-half_width[1], half_width[1])
        axes.set_aspect("equal")
        axes.set_xticks([])
        axes.set_yticks([])
        axes.set_title(f"{int(mask.sum())} options", color=colour, fontsize=TITLE_SIZE, fontweight="bold")
        # Below the map, not on it: a legend inside would hide part of the maze.
        figure.legend(
            *axes.get_legend_handles_labels(),
            loc="lower center",
            ncols=2,
            fontsize=LABEL_SIZE,
            frameon=False,
            handletextpad=0.4,
            columnspacing=1.0,
        )
        figure.tight_layout(rect=(0, 0.13, 1, 1))
        return figure

    # ---------------------------------------------------------------------------------------------------- robotics

    def _frame_strip_figure(self, pair: TrajectoryPairs, index: int, side: str, drawing: str) -> Figure:
        mask = pair.mask[index, 0]
        reached = pair.next_achieved_goals[index, 0, mask]
        goal = pair.observations["desired_goal"][index, 0, 0]
        steps = np.unique(np.linspace(0, len(reached) - 1, min(MAX_FRAMES - 1, len(reached))).round().astype(int))
        states = [("start", pair.observations["achieved_goal"][index, 0, 0])]
        states += [(f"after option {step + 1}", reached[step]) for step in steps]
        if drawing == KITCHEN:
            states.append(("goal", goal))
        columns = min(FRAMES_PER_ROW, len(states))
        rows = math.ceil(len(states) / columns)
        figure = Figure(figsize=(1.33 * columns, 1.45 * rows + 0.4))
        axes = np.atleast_1d(figure.subplots(rows, columns)).ravel()
        for axis in axes[len(states) :]:
            axis.axis("off")
        for axis, (title, achieved) in zip(axes[: len(states)], states, strict=True):
            axis.imshow(self._frame(achieved, goal, drawing))
            axis.set_title(title, fontsize=LABEL_SIZE, color="goldenrod" if title == "goal" else "black")
            axis.axis("off")
        figure.suptitle(f"{int(mask.sum())} options", color=COLOURS[side], fontsize=TITLE_SIZE, fontweight="bold")
        figure.tight_layout()
        return figure

    def _frame(self, achieved_goal: np.ndarray, goal: np.ndarray, drawing: str) -> np.ndarray:
        """The scene with ``achieved_goal`` put back into the simulation, as an RGB image."""
        import mujoco

        unwrapped: Any = self.env.unwrapped
        if drawing == KITCHEN:  # the task joints
            from gymnasium_robotics.envs.franka_kitchen.kitchen_env import OBS_ELEMENT_INDICES

            data, model = unwrapped.robot_env.data, unwrapped.robot_env.model
            offsets = np.cumsum([0, *(len(OBS_ELEMENT_INDICES[task]) for task in unwrapped.tasks)])
            for task, start, stop in zip(unwrapped.tasks, offsets[:-1], offsets[1:], strict=True):
                data.qpos[OBS_ELEMENT_INDICES[task]] = achieved_goal[start:stop]
            mujoco.mj_forward(model, data)
        else:  # Fetch: the object, or the gripper of FetchReach; the goal is the target site
            model, data = unwrapped.model, unwrapped.data
            unwrapped.goal = np.asarray(goal, dtype=np.float64).copy()
            if unwrapped.has_object:
                qpos = unwrapped._utils.get_joint_qpos(model, data, "object0:joint").copy()
                qpos[:3] = achieved_goal[:3]
                unwrapped._utils.set_joint_qpos(model, data, "object0:joint", qpos)
                mujoco.mj_forward(model, data)
            else:
                unwrapped._utils.set_mocap_pos(model, data, "robot0:mocap", achieved_goal[:3])
                for _ in range(10):
                    mujoco.mj_step(model, data, nstep=unwrapped.n_substeps)
            unwrapped._render_callback()
        frame = np.asarray(self.env.render())
        return frame[::2, ::2]
