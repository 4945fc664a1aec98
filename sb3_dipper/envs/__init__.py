"""Environments of this package, registered with gymnasium on ``import sb3_dipper``."""

import gymnasium as gym

from sb3_dipper.envs.point_maze import PointMazeExpert, PointMazeFourRoomsEnv, PointMazeReachController


def register_envs() -> None:
    """Register our env ids (idempotent)."""
    if "PointMazeFourRooms-v0" not in gym.registry:
        gym.register(
            id="PointMazeFourRooms-v0",
            entry_point="sb3_dipper.envs.point_maze:PointMazeFourRoomsEnv",
            max_episode_steps=200,
        )


__all__ = ["PointMazeExpert", "PointMazeFourRoomsEnv", "PointMazeReachController", "register_envs"]
