"""The option layer: higher-level actions in, K primitive steps of the lower level out.

:class:`OptionVecEnv` wraps the vectorised base goal env (``DummyVecEnv`` or ``SubprocVecEnv``, with ``Monitor``
inside and optionally ``VecNormalize``). One ``step(u)`` maps the higher-level actions ``u`` in ``[-1, 1]^d`` to
subgoals, runs the lower level for up to ``option_steps`` primitive steps on all envs in one batch (one forward pass of
the lower policy per primitive step, in this process), hands every primitive transition to a sink (the lower
learner), and returns the higher-level transition.

Design choice: the envs stay in lockstep. When any env's base episode ends, the option of *every* env ends at that
primitive step, so each env gets exactly one higher-level transition per ``step`` and the wrapper is a plain VecEnv.
With equal-length episodes (all our tasks: fixed horizons, no termination) envs start and end together, so this
never shortens an option; with terminating envs it shortens some options of the other envs, which stays a valid
(semi-Markov) higher-level transition. The lower-level segment then ends as a truncation (bootstrapped).

Internally everything (subgoals, lower observations, the lower buffer) uses the *original* observations; when the base
env is a ``VecNormalize``, the lower controller normalises its own inputs and ``step`` returns the normalised
observations a higher-level policy expects, as SB3's off-policy algorithms do.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper, VecNormalize, unwrap_vec_normalize
from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices, VecEnvObs, VecEnvStepReturn

from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.common.validation import check_finite

DictObs = dict[str, np.ndarray]


class LowLevelController(Protocol):
    """What the option layer needs from a lower level (a learned SAC or a scripted controller)."""

    def act(self, low_obs: DictObs, deterministic: bool) -> np.ndarray:
        """Primitive actions (in the env's action bounds) for a batch of lower-level observations."""

    def value(self, low_obs: DictObs) -> np.ndarray | None:
        """The lower level's value of reaching each subgoal, or ``None`` if it has none."""


@dataclass
class PrimitiveTransition:
    """One primitive step of all envs, as the lower learner sees it (original, unnormalised values)."""

    low_obs: DictObs
    actions: np.ndarray
    next_low_obs: DictObs
    low_rewards: np.ndarray
    segment_ends: np.ndarray
    base_rewards: np.ndarray
    base_dones: np.ndarray
    infos: list[dict[str, Any]]


# A sink returns False to stop training (a callback asked for it); the option then ends at once.
TransitionSink = Callable[[PrimitiveTransition], bool]


def low_level_observation(observation: DictObs, subgoals: np.ndarray, subgoal_space: SubgoalSpace) -> DictObs:
    """The lower level's goal-env observation: the env's ``observation``, the projected achieved goal, the subgoal."""
    return {
        "observation": np.asarray(observation["observation"], dtype=np.float32),
        "achieved_goal": np.asarray(subgoal_space.project(observation["achieved_goal"]), dtype=np.float32),
        "desired_goal": np.asarray(subgoals, dtype=np.float32),
    }


class LevelVecEnv(VecEnv):
    """One level's env as SB3 sees it: its spaces and ``env_method``, never reset nor stepped.

    The option layer (:class:`OptionVecEnv`) drives the base env; an SB3 learner of one level (a lower or higher SAC
    with ``HerReplayBuffer``) still needs a ``VecEnv`` with that level's spaces, and HER calls its ``compute_reward``
    through ``env_method``, which a subclass provides.

    :param observation_space: the level's observation space
    :param action_space: the level's action space
    :param num_envs: number of parallel envs of the option layer
    :param level: the level, named in the error of a reset or step (``"lower"``, ``"higher"``)
    """

    def __init__(self, observation_space: spaces.Space, action_space: spaces.Space, num_envs: int, level: str) -> None:
        # VecEnv.__init__ asks the envs for their render_mode and warns when there is none; this facade renders nothing.
        self.render_mode = None
        super().__init__(num_envs, observation_space, action_space)
        self.level = level

    def _not_stepped(self) -> RuntimeError:
        return RuntimeError(
            f"The {self.level} level's env is driven by the option layer; it cannot be reset or stepped directly."
        )

    def reset(self) -> VecEnvObs:
        raise self._not_stepped()

    def step_async(self, actions: np.ndarray) -> None:
        raise self._not_stepped()

    def step_wait(self) -> VecEnvStepReturn:
        raise self._not_stepped()

    def close(self) -> None:
        pass

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [getattr(self, attr_name) for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        setattr(self, attr_name, value)

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def seed(self, seed: int | None = None) -> Sequence[int | None]:
        return [None for _ in range(self.num_envs)]


class OptionVecEnv(VecEnvWrapper):
    """VecEnv of options: each step runs the lower level for ``option_steps`` primitive steps toward a subgoal.

    :param venv: the vectorised base goal env
    :param subgoal_space: maps higher-level actions to subgoals
    :param option_steps: K, the number of primitive steps per option
    :param low_level: the lower-level controller
    :param sink: receives every primitive transition (for example the lower learner's replay buffer)
    :param deterministic: whether the lower level acts deterministically
    """

    def __init__(
        self,
        venv: VecEnv,
        subgoal_space: SubgoalSpace,
        option_steps: int,
        low_level: LowLevelController,
        sink: TransitionSink | None = None,
        deterministic: bool = False,
    ) -> None:
        if option_steps < 1:
            raise ValueError(f"option_steps must be at least 1, got {option_steps}")
        super().__init__(venv, observation_space=venv.observation_space, action_space=subgoal_space.unit_box)
        self.subgoal_space = subgoal_space
        self.option_steps = option_steps
        self.low_level = low_level
        self.sink = sink
        self.deterministic = deterministic
        self.vec_normalize: VecNormalize | None = unwrap_vec_normalize(venv)
        self.original_obs: DictObs | None = None
        # Where the last option ended, original values, with the terminal observation of envs whose episode ended.
        self.reached_obs: DictObs | None = None
        self._subgoals: np.ndarray | None = None

    def _original(self, obs: DictObs) -> DictObs:
        if self.vec_normalize is None:
            return obs
        return self.vec_normalize.get_original_obs()  # type: ignore[return-value]

    def _original_terminal(self, info: dict[str, Any]) -> DictObs:
        terminal = info["terminal_observation"]
        if self.vec_normalize is None:
            return terminal
        return self.vec_normalize.unnormalize_obs(terminal)  # type: ignore[return-value]

    def reset(self) -> VecEnvObs:
        obs = self.venv.reset()
        self.observe_reset(obs)  # type: ignore[arg-type]
        return obs

    def observe_reset(self, obs: DictObs) -> None:
        """Take note of observations after the base env was reset by someone else (SB3's ``_setup_learn``)."""
        self.original_obs = {key: np.array(value) for key, value in self._original(obs).items()}
        check_finite(self.original_obs)

    def step_async(self, actions: np.ndarray) -> None:
        self._subgoals = self.subgoal_space.to_world(np.asarray(actions).reshape(self.num_envs, -1))

    def step_wait(self) -> VecEnvStepReturn:
        assert self._subgoals is not None and self.original_obs is not None, "call reset() and step_async() first"
        subgoals = self._subgoals
        space = self.subgoal_space
        original = self.original_obs
        low_value = self.low_level.value(low_level_observation(original, subgoals, space))
        for step in range(self.option_steps):
            low_obs = low_level_observation(original, subgoals, space)
            actions = self.low_level.act(low_obs, self.deterministic)
            obs, rewards, dones, infos = self.venv.step(actions)
            next_original = self._original(obs)  # type: ignore[arg-type]
            check_finite(next_original)
            reached = {key: value.copy() for key, value in next_original.items()}
            ended = np.flatnonzero(dones)
            for env_idx in ended:
                for key, value in self._original_terminal(infos[env_idx]).items():
                    reached[key][env_idx] = value
            # The terminal observations replace the checked ones of ended envs: they go to the buffers too.
            terminal = {key: value[ended] for key, value in reached.items()}
            check_finite(terminal, ended, "Terminal observation (info['terminal_observation'])")
            next_low_obs = low_level_observation(reached, subgoals, space)
            option_ends = bool(dones.any()) or step == self.option_steps - 1
            keep_going = True
            if self.sink is not None:
                keep_going = self.sink(
                    PrimitiveTransition(
                        low_obs=low_obs,
                        actions=actions,
                        next_low_obs=next_low_obs,
                        low_rewards=space.compute_reward(next_low_obs["achieved_goal"], subgoals),
                        segment_ends=np.full(self.num_envs, option_ends),
                        base_rewards=rewards,
                        base_dones=dones,
                        infos=infos,
                    )
                )
            original = next_original
            if option_ends or not keep_going:
                break
        self.original_obs = original
        self.reached_obs = reached
        distances = space.distance(next_low_obs["achieved_goal"], subgoals)
        for index, info in enumerate(infos):
            info["subgoal"] = subgoals[index]
            info["achieved_subgoal"] = next_low_obs["achieved_goal"][index]
            info["subgoal_distance"] = float(distances[index])
            info["option_steps"] = step + 1
            info["option_interrupted"] = not keep_going
            if low_value is not None:
                info["low_value"] = float(low_value[index])
        return obs, rewards, dones, infos
