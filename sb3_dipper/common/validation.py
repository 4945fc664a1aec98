"""Input checks that turn common mistakes into errors naming the problem and the fix."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv

GOAL_KEYS = ("observation", "achieved_goal", "desired_goal")


def check_goal_observation_space(observation_space: spaces.Space, algorithm: str) -> None:
    """Refuse envs that are not flat goal envs before SB3 wraps them (its own errors are less helpful)."""
    if not isinstance(observation_space, spaces.Dict) or not set(GOAL_KEYS) <= set(observation_space.spaces):
        raise ValueError(
            f"{algorithm} needs a goal-conditioned env: observations must be a Dict with keys {GOAL_KEYS} "
            f"(gymnasium-robotics style, with a vectorised compute_reward), but got {observation_space}. "
            "Use a goal env such as PointMazeFourRooms-v0 or FetchPush-v4, or wrap yours to expose these keys."
        )
    for key, space in observation_space.spaces.items():
        if isinstance(space, spaces.Dict):
            raise ValueError(
                f"{algorithm} needs flat Box observations, but key {key!r} is a nested Dict ({space}). "
                "Flatten the goals into Boxes (FrankaKitchen-v1 needs this: use FrankaKitchenMicrowaveBurner-v0)."
            )
        if not isinstance(space, spaces.Box) or len(space.shape) != 1:
            raise ValueError(f"{algorithm} needs 1-D Box spaces for every observation key, but {key!r} is {space}.")


def sparse_goal_reached_fn(venv: VecEnv) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """``goal_reached(achieved, desired)`` from the env's own vectorised ``compute_reward``.

    A goal counts as reached where the reward equals the reward of an achieved goal equal to the desired one, so
    any sparse convention (-1/0 or 0/1) works. Dense rewards have no such level and are refused.
    """
    goal_dim = venv.observation_space["achieved_goal"].shape[0]  # type: ignore[index]

    def rewards(achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        infos: list[dict[str, Any]] = [{} for _ in range(achieved.shape[0])]
        return np.asarray(venv.env_method("compute_reward", achieved, desired, infos, indices=[0])[0], dtype=np.float64)

    # Goal pairs from far apart to identical: a sparse reward takes one value for reached goals and one for the rest.
    rng = np.random.default_rng(0)
    achieved = rng.normal(size=(64, goal_dim)).astype(np.float32)
    desired = achieved + np.logspace(-4, 2, 64, dtype=np.float32)[:, None] * rng.normal(size=(64, goal_dim)).astype(np.float32)
    probe = rewards(achieved, desired)
    if probe.shape != (64,):
        raise ValueError(
            f"The env's compute_reward must be vectorised (a batch of 64 goals gave shape {probe.shape}); "
            "SB3's HerReplayBuffer and the preference labels both need that."
        )
    success_reward = rewards(achieved[:1], achieved[:1])[0]
    if np.unique(np.append(probe, success_reward)).size > 2:
        raise ValueError(
            "Preference labels need a sparse goal reward (one value when the goal is reached, one otherwise), "
            f"but compute_reward gave {np.unique(probe).size} different values on 64 goal pairs: is the reward dense?"
        )

    def goal_reached(achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        flat_achieved = achieved.reshape(-1, goal_dim)
        flat_desired = np.broadcast_to(desired, achieved.shape).reshape(-1, goal_dim)
        reached = np.isclose(rewards(flat_achieved, flat_desired), success_reward)
        return reached.reshape(achieved.shape[:-1])

    return goal_reached
