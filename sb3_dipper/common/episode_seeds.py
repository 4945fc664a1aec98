"""Episodes drawn from a seed stream, so that two envs can replay the same episodes (twin episodes).

A task with random layouts, starts or goals draws them at ``reset``. Two copies of it whose resets draw their seeds
from the same stream play the same sequence of episodes, whatever their policies do in between: their ``k``-th
episodes share layout, start and goal. DIPPER's ``twin_episodes`` switch drives one copy by its policy and the other
by the goal as every subgoal, and compares the two trajectories of each episode.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

#: the key of a step's ``info`` (and a reset's) that holds the seed of the episode it belongs to
EPISODE_SEED_KEY = "episode_seed"


class EpisodeSeeds(gym.Wrapper):
    """Once :meth:`seed_episodes` is called, every reset draws its seed from a stream of that seed, and every step's
    and reset's ``info`` holds the episode's seed under ``"episode_seed"`` (the fact that two episodes are the same,
    from the code that seeded them). Before it is called the wrapper changes nothing (an evaluation env keeps its
    episodes).

    A seed passed to ``reset`` while a stream is set is not used (a ``VecEnv`` passes ``seed + env_index`` at its
    first reset, which would part the twins): call :meth:`seed_episodes` again to start another stream.

    :param env: the env whose episodes the stream seeds
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self._stream: np.random.Generator | None = None
        self._episode_seed: int | None = None

    @property
    def episodes_seeded(self) -> bool:
        """Whether a stream seeds the resets (:meth:`seed_episodes` was called)."""
        return self._stream is not None

    def seed_episodes(self, seed: int) -> None:
        """Draw the seed of every following reset from a stream seeded with ``seed``."""
        self._stream = np.random.default_rng(seed)
        self._episode_seed = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        if self._stream is None:
            return self.env.reset(seed=seed, options=options)
        self._episode_seed = int(self._stream.integers(2**62))
        obs, info = self.env.reset(seed=self._episode_seed, options=options)
        return obs, {**info, EPISODE_SEED_KEY: self._episode_seed}

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        if self._episode_seed is not None:
            info = {**info, EPISODE_SEED_KEY: self._episode_seed}
        return obs, reward, terminated, truncated, info
