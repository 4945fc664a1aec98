"""gymnasium-robotics' own goal envs out of the box: subgoal spaces for Fetch reach and slide and for every maze.

Their ``achieved_goal`` boxes are unbounded, so :func:`~sb3_dipper.common.subgoals.resolve_subgoal_space` cannot derive a
subgoal space from them; :func:`register_robotics_envs` declares one per env id instead:

- ``FetchReach-v4`` and ``FetchSlide-v4`` (and their ``Dense`` variants): the box the env draws its goals from (and, for
  slide, its object starts), read from the env's own ``initial_gripper_xpos``, ``target_offset``, ``target_range`` and
  ``obj_range``; the threshold is the env's ``distance_threshold``. Upstream already reports ``info["is_success"]``.
- every ``PointMaze_*`` and ``AntMaze_*`` id, sparse and dense, all versions: the bounding box of the map's open cells,
  from the env's maze map and cell size, with the mazes' success radius of 0.45 as threshold. The mazes report
  ``info["success"]`` rather than SB3's ``info["is_success"]``, so their registrations also get :class:`MazeIsSuccess`
  as an additional wrapper: ``gym.make`` applies it, inside SB3's ``Monitor``, which then finds the key it records.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.envs.registration import WrapperSpec

from sb3_dipper.common.subgoals import SubgoalSpace, register_subgoal_space

# gymnasium-robotics' MazeEnv hard-codes its success radius (compute_reward, compute_terminated, info["success"]).
MAZE_GOAL_RADIUS = 0.45
# Half the height of a Fetch object (a 5 cm cube): how far its centre may sit from its resting height.
FETCH_OBJECT_HALF_SIZE = 0.025
# Upstream draws the goals of object tasks with ``target_in_the_air`` up to this height above the resting object.
FETCH_AIR_GOAL_HEIGHT = 0.45

FETCH_IDS = ("FetchReach-v4", "FetchReachDense-v4", "FetchSlide-v4", "FetchSlideDense-v4")
MAZE_ENTRY_POINT_PREFIX = "gymnasium_robotics.envs.maze."


def fetch_subgoal_space(env: gym.Env) -> SubgoalSpace:
    """The region a Fetch task draws its goals from (and, with an object, the object's start), as the env defines it.

    :param env: the unwrapped Fetch env (its goal and object sampling ranges are read from it)
    """
    fetch: Any = env.unwrapped
    centre = np.asarray(fetch.initial_gripper_xpos[:3], dtype=np.float64) + fetch.target_offset
    low, high = centre - fetch.target_range, centre + fetch.target_range
    if fetch.has_object:
        # The object starts around the gripper and is the achieved goal, so subgoals cover its start region too.
        object_start = np.asarray(fetch.initial_gripper_xpos[:2], dtype=np.float64)
        low[:2] = np.minimum(low[:2], object_start - fetch.obj_range)
        high[:2] = np.maximum(high[:2], object_start + fetch.obj_range)
        low[2] = fetch.height_offset - FETCH_OBJECT_HALF_SIZE
        high[2] = fetch.height_offset + (FETCH_AIR_GOAL_HEIGHT if fetch.target_in_the_air else FETCH_OBJECT_HALF_SIZE)
    return SubgoalSpace(low=low, high=high, threshold=float(fetch.distance_threshold))


def maze_subgoal_space(env: gym.Env) -> SubgoalSpace:
    """The bounding box of a maze's open cells (every cell that is not a wall), from its map and cell size.

    :param env: the unwrapped PointMaze or AntMaze env (its ``maze`` is read)
    """
    maze = env.unwrapped.maze  # type: ignore[attr-defined]
    open_cells = [
        maze.cell_rowcol_to_xy(np.array([row, col]))
        for row, cells in enumerate(maze.maze_map)
        for col, cell in enumerate(cells)
        if cell != 1
    ]
    half_cell = 0.5 * maze.maze_size_scaling
    return SubgoalSpace(
        low=np.min(open_cells, axis=0) - half_cell,
        high=np.max(open_cells, axis=0) + half_cell,
        threshold=MAZE_GOAL_RADIUS,
    )


class MazeIsSuccess(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Report a maze's ``info["success"]`` also as ``info["is_success"]`` (a float), the key SB3 reads.

    ``AntMaze-v3`` reports no ``success``: there it is recomputed from the goal distance, as later versions do.

    :param env: a gymnasium-robotics PointMaze or AntMaze env
    """

    def __init__(self, env: gym.Env) -> None:
        gym.utils.RecordConstructorArgs.__init__(self)
        gym.Wrapper.__init__(self, env)

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        if "success" in info:
            success = bool(info["success"])
        else:
            success = bool(np.linalg.norm(obs["achieved_goal"] - obs["desired_goal"]) <= MAZE_GOAL_RADIUS)
        info["is_success"] = float(success)
        return obs, reward, terminated, truncated, info


MAZE_IS_SUCCESS = WrapperSpec(name="MazeIsSuccess", entry_point="sb3_dipper.envs.robotics:MazeIsSuccess", kwargs={})


def maze_env_ids() -> list[str]:
    """Every registered gymnasium-robotics maze id (``PointMaze_*`` and ``AntMaze_*``, sparse and dense)."""
    return [
        env_id
        for env_id, spec in gym.registry.items()
        if isinstance(spec.entry_point, str) and spec.entry_point.startswith(MAZE_ENTRY_POINT_PREFIX)
    ]


def register_robotics_envs() -> None:
    """Declare the subgoal spaces of gymnasium-robotics' Fetch reach, slide and mazes; add ``is_success`` to the mazes.

    Idempotent. The maze ids keep their registration (entry point, kwargs, time limit) with :class:`MazeIsSuccess`
    appended to its additional wrappers.
    """
    for env_id in FETCH_IDS:
        register_subgoal_space(env_id, fetch_subgoal_space)
    for env_id in maze_env_ids():
        register_subgoal_space(env_id, maze_subgoal_space)
        spec = gym.registry[env_id]
        if MAZE_IS_SUCCESS not in spec.additional_wrappers:
            gym.registry[env_id] = dataclasses.replace(spec, additional_wrappers=(*spec.additional_wrappers, MAZE_IS_SUCCESS))
