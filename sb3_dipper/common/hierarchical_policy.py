"""Both levels of a trained hierarchy as one policy from observations to primitive actions, without the algorithm.

A hierarchical algorithm keeps SB3's ``model.policy`` attribute (saving, the zoo and callbacks rely on it), but that is
its *higher-level* policy: ``model.policy.predict`` returns a higher-level action in ``[-1, 1]^d`` (a subgoal, in the
coordinates ``subgoal_space.to_world`` maps to the goal space), not a primitive action. ``model.predict`` runs both
levels; :class:`HierarchicalPolicy`, from ``model.export_policy()``, runs them the same way without the algorithm (no
replay buffers, envs or optimizers' training loop): the higher policy, the lower policy, the subgoal space, the option
length K and the ``VecNormalize`` statistics the lower level normalises with. ``model.predict`` itself acts through a
:class:`HierarchicalPolicy`, so both give the same actions.

Observations are what the (possibly ``VecNormalize``-d) env returns, batched or not; the recurrent ``state``
``(subgoals, steps_left)`` carries the current option between calls, as with ``model.predict``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.sac.policies import SACPolicy

from sb3_dipper.common.low_level import SubgoalNormalizer
from sb3_dipper.common.option_env import DictObs, low_level_observation
from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.common.validation import checked_goal_observation

# Higher-level actions in [-1, 1]^d for a batch of (normalised) observations: (observation, deterministic) -> actions.
HighLevelActions = Callable[[DictObs, bool], np.ndarray]
OptionState = tuple[np.ndarray, np.ndarray]


class ActingLowLevel(Protocol):
    """What acting needs from a lower level: primitive actions for lower observations (already normalised)."""

    def act(self, low_obs: DictObs, deterministic: bool, normalized: bool = False) -> np.ndarray:
        """Primitive actions for a batch of lower-level observations."""


def copy_policy(policy: BasePolicy) -> BasePolicy:
    """A copy of an SB3 policy built from its constructor parameters and weights, as SB3's ``BasePolicy.load`` does.

    Unlike ``copy.deepcopy`` it leaves the optimizers' state behind, and with it any hook into the algorithm (SAGA's
    actor optimizer has one), and it draws no random numbers from the training run.
    """
    with th.random.fork_rng(devices=[]):
        copied = type(policy)(**policy._get_constructor_parameters()).to(policy.device)
    copied.load_state_dict(policy.state_dict())
    copied.set_training_mode(False)
    return copied


class PolicyHighLevel:
    """A higher level that acts with its policy alone: ``policy.predict``, one row per env.

    :param policy: the higher-level policy (its action space is ``[-1, 1]^d``)
    """

    def __init__(self, policy: BasePolicy) -> None:
        self.policy = policy

    def __deepcopy__(self, memo: dict[int, Any]) -> PolicyHighLevel:
        return PolicyHighLevel(copy_policy(self.policy))

    def __call__(self, observation: DictObs, deterministic: bool) -> np.ndarray:
        actions, _ = self.policy.predict(observation, deterministic=deterministic)  # type: ignore[arg-type]
        return np.asarray(actions, dtype=np.float32).reshape(-1, self.policy.action_space.shape[0])  # type: ignore[index]


class SACPolicyLowLevel:
    """A lower level that acts with a SAC policy on normalised lower observations (no exploration, no buffer).

    :param policy: the lower SAC's policy
    """

    def __init__(self, policy: SACPolicy) -> None:
        self.policy = policy

    def __deepcopy__(self, memo: dict[int, Any]) -> SACPolicyLowLevel:
        return SACPolicyLowLevel(copy_policy(self.policy))  # type: ignore[arg-type]

    def act(self, low_obs: DictObs, deterministic: bool, normalized: bool = True) -> np.ndarray:
        """Primitive actions; ``low_obs`` must already be normalised (``normalized=False`` is refused)."""
        if not normalized:
            raise ValueError("SACPolicyLowLevel acts on normalised lower observations: normalise them first")
        tensors = {key: th.as_tensor(value, dtype=th.float32, device=self.policy.device) for key, value in low_obs.items()}
        with th.no_grad():
            scaled = self.policy.actor(tensors, deterministic=deterministic).cpu().numpy()
        return self.policy.unscale_action(scaled)


class HierarchicalPolicy:
    """A two-level policy: every ``option_steps`` steps the higher level proposes a subgoal, the lower level acts toward it.

    :param high_level: higher-level actions in ``[-1, 1]^d`` for a batch of observations (e.g. :class:`PolicyHighLevel`)
    :param low_level: the lower level (e.g. :class:`SACPolicyLowLevel`)
    :param subgoal_space: maps higher-level actions to subgoals and projects achieved goals
    :param option_steps: K, the primitive steps per subgoal
    :param observation_space: the env's observation space (a goal env's Dict space)
    :param action_space: the env's (Box) action space; actions are clipped to it
    :param normalizer: the ``VecNormalize`` statistics the lower level normalises with (``None``: no normalisation)
    """

    def __init__(
        self,
        high_level: HighLevelActions,
        low_level: ActingLowLevel,
        subgoal_space: SubgoalSpace,
        option_steps: int,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        normalizer: SubgoalNormalizer | None = None,
    ) -> None:
        self.high_level = high_level
        self.low_level = low_level
        self.subgoal_space = subgoal_space
        self.option_steps = option_steps
        self.observation_space = observation_space
        self.action_space = action_space
        self.normalizer = normalizer

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, OptionState]:
        """A primitive action; ``state = (subgoals, steps_left)`` carries the current option between calls.

        :param observation: what the (possibly ``VecNormalize``-d) env returns, batched or not
        :param state: the state the previous call returned (``None``: every env starts a new option)
        :param episode_start: envs whose episode just started start a new option
        :param deterministic: whether both levels act deterministically
        """
        batch, vectorized = checked_goal_observation(observation, self.observation_space)
        n_envs = batch["desired_goal"].shape[0]
        if state is None:
            subgoals, steps_left = np.zeros((n_envs, self.subgoal_space.dim), dtype=np.float32), np.zeros(n_envs, np.int64)
        else:
            subgoals, steps_left = self._checked_state(state, n_envs)
        new_option = steps_left <= 0
        if episode_start is not None:
            starts = np.asarray(episode_start, dtype=bool).reshape(-1)
            if starts.size != n_envs:
                # A single flag would start a new option in every env, cutting the others' options short.
                raise ValueError(f"predict: episode_start has {starts.size} entries for {n_envs} envs: give one per env")
            new_option |= starts
        if new_option.any():
            high_actions = self.high_level(batch, deterministic)
            subgoals[new_option] = self.subgoal_space.to_world(high_actions[new_option])
            steps_left[new_option] = self.option_steps
        normalized_subgoals = subgoals if self.normalizer is None else self.normalizer.normalize_subgoal(subgoals)
        low_obs = low_level_observation(batch, normalized_subgoals, self.subgoal_space)
        actions = self.low_level.act(low_obs, deterministic, normalized=True)
        actions = np.clip(actions, self.action_space.low, self.action_space.high)
        if not vectorized:
            actions = actions.squeeze(axis=0)
        return actions, (subgoals, steps_left - 1)

    def _checked_state(self, state: tuple[np.ndarray, ...], n_envs: int) -> OptionState:
        """``state`` as ``(subgoals, steps_left)`` arrays of their own, refused unless it is the options of ``n_envs``
        envs in this policy's subgoal space."""
        expected = (n_envs, self.subgoal_space.dim)
        given = [np.shape(part) for part in state]
        if len(state) != 2 or given[0] != expected or given[1] != (n_envs,):
            raise ValueError(
                f"predict: state must be the (subgoals, steps_left) the previous call returned, of shapes {expected} "
                f"and ({n_envs},) for this observation's {n_envs} env(s), got shapes {', '.join(map(str, given))}; "
                "pass state=None when the envs change (every env starts a new option)"
            )
        return np.array(state[0], dtype=np.float32), np.array(state[1], dtype=np.int64)
