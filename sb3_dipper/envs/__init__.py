"""Environments of this package, registered with gymnasium on ``import sb3_dipper``, and their scripted experts."""

from collections.abc import Callable
from functools import partial
from typing import Any

import gymnasium as gym

from sb3_dipper.common.demonstrations import register_default_demonstrations
from sb3_dipper.envs import fetch, kitchen, robotics
from sb3_dipper.envs.demos import default_demonstrations
from sb3_dipper.envs.point_maze import PointMazeExpert, PointMazeFourRoomsEnv, PointMazeReachController

# env id -> factory(env) of a scripted expert with reset() and act(observation) (see sb3_dipper.common.demonstrations)
EXPERTS: dict[str, Callable[[gym.Env], Any]] = {
    "PointMazeFourRooms-v0": lambda env: PointMazeExpert(),
    **fetch.EXPERTS,
    **kitchen.EXPERTS,
}


def register_envs() -> None:
    """Register our env ids and, for ``demo_path="auto"`` and ``"auto:dart<N>"``, each expert's demonstrations (idempotent)."""
    for env_id in EXPERTS:
        register_default_demonstrations(env_id, partial(default_demonstrations, env_id))
    if "PointMazeFourRooms-v0" not in gym.registry:
        gym.register(
            id="PointMazeFourRooms-v0",
            entry_point="sb3_dipper.envs.point_maze:PointMazeFourRoomsEnv",
            max_episode_steps=200,
        )
    fetch.register_fetch_envs()
    kitchen.register_kitchen_envs()
    robotics.register_robotics_envs()


__all__ = ["EXPERTS", "PointMazeExpert", "PointMazeFourRoomsEnv", "PointMazeReachController", "register_envs"]
