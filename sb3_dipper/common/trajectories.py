"""Whole higher-level trajectories, the raw material of preference pairs.

A trajectory is the sequence of higher-level decisions of one base-env episode: for each option ``t`` the observation
``s_t`` (original values, all keys), the higher-level action ``u_t`` in ``[-1, 1]^d`` and the achieved goal
``ag_{t+1}`` reached when the option ended. Trajectories are stored padded to ``max_length`` with a mask, each with
whether the env's goal was every subgoal of it (:attr:`TrajectoryBuffer.goal_driven`: the goal-driven control's
trajectories, which DIPPER's ``goal_episode_prob`` collects) and, where an
:class:`~sb3_dipper.common.episode_seeds.EpisodeSeeds` stream seeded its episode, that episode's seed
(:attr:`TrajectoryBuffer.episode_seeds`: two trajectories with one seed played the same episode).
"""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

DictObs = dict[str, np.ndarray]


class TrajectoryBuffer:
    """Circular buffer of completed higher-level trajectories.

    :param capacity: number of trajectories kept
    :param max_length: T, the most higher-level steps an episode can have
    :param observation_space: the base env's Dict observation space
    :param action_dim: dimension of the higher-level action
    :param n_envs: number of parallel envs feeding the buffer
    """

    def __init__(
        self, capacity: int, max_length: int, observation_space: spaces.Dict, action_dim: int, n_envs: int = 1
    ) -> None:
        self.capacity = capacity
        self.max_length = max_length
        self.n_envs = n_envs
        self.observations = {
            key: np.zeros((capacity, max_length, *(space.shape or ())), dtype=np.float32)
            for key, space in observation_space.spaces.items()
        }
        goal_shape = observation_space["achieved_goal"].shape or ()
        self.actions = np.zeros((capacity, max_length, action_dim), dtype=np.float32)
        self.next_achieved_goals = np.zeros((capacity, max_length, *goal_shape), dtype=np.float32)
        self.lengths = np.zeros(capacity, dtype=np.int64)
        # Whether the env's goal was the subgoal at every step (the collector says so; nothing compares subgoals).
        self.goal_driven = np.zeros(capacity, dtype=bool)
        # The seed of the episode a trajectory played from its start, as the env reported it; -1: no seed reported,
        # or a trajectory continuing an episode that outlasted max_length (its twin's continuation may differ).
        self.episode_seeds = np.full(capacity, -1, dtype=np.int64)
        self.pos = 0
        self.full = False
        self._open: list[list[tuple[DictObs, np.ndarray, np.ndarray]]] = [[] for _ in range(n_envs)]
        self._open_goal_driven = np.ones(n_envs, dtype=bool)
        self._open_seeds = np.full(n_envs, -1, dtype=np.int64)
        self._open_starts_episode = np.ones(n_envs, dtype=bool)

    def __len__(self) -> int:
        return self.capacity if self.full else self.pos

    def add(
        self,
        obs: DictObs,
        actions: np.ndarray,
        next_achieved_goals: np.ndarray,
        dones: np.ndarray,
        goal_driven: np.ndarray | None = None,
        episode_seeds: np.ndarray | None = None,
    ) -> None:
        """Add one higher-level step of every env (original observations); close the trajectories of done envs.

        :param goal_driven: per env, whether this step's subgoal was the env's goal (``None``: no env's was); a
            trajectory is :attr:`goal_driven` if every one of its steps was
        :param episode_seeds: per env, the seed of the episode this step belongs to (-1 or ``None``: not known)
        """
        if episode_seeds is not None:
            self._open_seeds[:] = episode_seeds
        if goal_driven is None:
            self._open_goal_driven[:] = False
        else:
            self._open_goal_driven &= np.asarray(goal_driven, dtype=bool)
        for env_idx in range(self.n_envs):
            step_obs = {key: value[env_idx].copy() for key, value in obs.items()}
            self._open[env_idx].append((step_obs, actions[env_idx].copy(), next_achieved_goals[env_idx].copy()))
            if dones[env_idx] or len(self._open[env_idx]) == self.max_length:
                self._close(env_idx, ended_episode=bool(dones[env_idx]))

    def _close(self, env_idx: int, ended_episode: bool) -> None:
        steps = self._open[env_idx]
        self._open[env_idx] = []
        length = len(steps)
        for key, store in self.observations.items():
            store[self.pos] = 0.0
            store[self.pos, :length] = np.stack([step[0][key] for step in steps])
        self.actions[self.pos] = 0.0
        self.actions[self.pos, :length] = np.stack([step[1] for step in steps])
        self.next_achieved_goals[self.pos] = 0.0
        self.next_achieved_goals[self.pos, :length] = np.stack([step[2] for step in steps])
        self.lengths[self.pos] = length
        self.goal_driven[self.pos] = self._open_goal_driven[env_idx]
        self.episode_seeds[self.pos] = self._open_seeds[env_idx] if self._open_starts_episode[env_idx] else -1
        self._open_goal_driven[env_idx] = True
        self._open_starts_episode[env_idx] = ended_episode
        self._open_seeds[env_idx] = -1
        self.pos = (self.pos + 1) % self.capacity
        self.full = self.full or self.pos == 0

    def discard_open(self) -> None:
        """Drop unfinished trajectories (their env is being reset)."""
        self._open = [[] for _ in range(self.n_envs)]
        self._open_goal_driven[:] = True
        self._open_seeds[:] = -1
        self._open_starts_episode[:] = True

    def mask(self, indices: np.ndarray) -> np.ndarray:
        """``(len(indices), max_length)`` booleans: which steps of each trajectory are real."""
        return np.arange(self.max_length)[None, :] < self.lengths[indices][:, None]

    def state_dict(self) -> dict[str, np.ndarray]:
        """Arrays to save (npz-friendly); open trajectories are not saved, as SB3 truncates open episodes."""
        arrays: dict[str, np.ndarray] = {f"observations/{key}": value for key, value in self.observations.items()}
        arrays.update(
            actions=self.actions,
            next_achieved_goals=self.next_achieved_goals,
            lengths=self.lengths,
            goal_driven=self.goal_driven,
            episode_seeds=self.episode_seeds,
            position=np.array([self.pos, int(self.full)]),
        )
        return arrays

    def load_state_dict(self, arrays: dict[str, np.ndarray]) -> None:
        for key in self.observations:
            self.observations[key][...] = arrays[f"observations/{key}"]
        self.actions[...] = arrays["actions"]
        self.next_achieved_goals[...] = arrays["next_achieved_goals"]
        self.lengths[...] = arrays["lengths"]
        self.goal_driven[...] = arrays["goal_driven"]
        self.episode_seeds[...] = arrays["episode_seeds"]
        self.pos, full = (int(value) for value in arrays["position"])
        self.full = bool(full)
        self.discard_open()
