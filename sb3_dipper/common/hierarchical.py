"""Shared machinery of two-level algorithms on the option layer (DIPPER, HIER and the hierarchical baselines).

:class:`HierarchicalAlgorithm` is to our algorithms what SB3's ``OffPolicyAlgorithm`` is to SAC: it owns the lower
level (an SB3 ``SAC`` with ``HerReplayBuffer`` on subgoals), the option layer, the learn loop, ``predict`` and
saving. A subclass decides how the higher level acts, what it stores and how it trains.

Counting follows SB3 so flat and hierarchical curves share one x-axis: ``num_timesteps`` counts primitive env steps,
callbacks' ``on_step`` runs once per primitive step, ``rollout/success_rate`` comes from base-env episodes.
``predict`` returns a primitive action; the recurrent ``state`` carries ``(subgoals, steps_left)``, so SB3's
``evaluate_policy``, ``EvalCallback`` and the zoo's ``enjoy`` drive a hierarchical policy unchanged.
"""

from __future__ import annotations

import copy
import io
import math
import pathlib
import sys
import time
import warnings
from abc import abstractmethod
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import check_for_correct_spaces, safe_mean
from stable_baselines3.common.vec_env import VecEnv, VecNormalize, unwrap_vec_normalize
from stable_baselines3.her.her_replay_buffer import HerReplayBuffer

from sb3_dipper.common.demonstrations import Demonstrations, demonstrations_for, normalize_like_demonstrations
from sb3_dipper.common.deprecation import MovedParameter
from sb3_dipper.common.files import read_replay_buffer, replay_buffer_path, save_replay_buffer_file
from sb3_dipper.common.hierarchical_policy import (
    ActingLowLevel,
    HierarchicalPolicy,
    HighLevelActions,
    PolicyHighLevel,
    SACPolicyLowLevel,
)
from sb3_dipper.common.imitation import DEFAULT_DEMO_KWARGS, DemonstrationBuffer, DemoSAC, checked_demo_kwargs
from sb3_dipper.common.loading import CheckedLoading, unchanged_on_failure
from sb3_dipper.common.low_level import (
    LevelLogger,
    SACLowLevel,
    SubgoalNormalizer,
    SubgoalVecEnv,
    low_level_observation_space,
    sac_dead_units,
    sac_torch_save_params,
)
from sb3_dipper.common.option_env import DictObs, OptionVecEnv, PrimitiveTransition
from sb3_dipper.common.subgoals import SubgoalSpace, check_subgoal_space, resolve_subgoal_space
from sb3_dipper.common.trajectories import TrajectoryBuffer
from sb3_dipper.common.validation import (
    EnvGoalReward,
    InvalidSetting,
    as_entropy_coefficient,
    as_float,
    as_int,
    as_learning_rate,
    as_optional_int,
    check_keyword_arguments,
    checked_her_kwargs,
    policy_class_and_goal_env,
)

SelfHierarchicalAlgorithm = TypeVar("SelfHierarchicalAlgorithm", bound="HierarchicalAlgorithm")

# A lower buffer that is only loaded to predict needs no room: one HER "episode" of a few transitions.
PREDICT_ONLY_BUFFER_SIZE = 16


class HierarchicalAlgorithm(CheckedLoading):
    """Base class of two-level algorithms: a higher level proposes subgoals, a lower SAC+HER reaches them.

    Callbacks follow SB3's off-policy loop, where a *rollout* is one option of every env (at most ``option_steps``
    primitive steps, fewer when an episode ends): ``on_rollout_start`` before the higher level proposes the subgoals,
    ``on_step`` after every primitive step, ``on_rollout_end`` once the option is stored and before the training round
    that follows it. As in SB3, a callback's ``on_step`` returning False stops training at once, without
    ``on_rollout_end``; the option ends there, is stored like any shortened option, and ``learn(...,
    reset_num_timesteps=False)`` resumes from where the env is.

    ``policy`` is SB3's attribute, the *higher-level* policy: ``policy.predict`` returns a higher-level action in
    ``[-1, 1]^d`` (a subgoal), not a primitive action. :meth:`predict` runs both levels; :meth:`export_policy` returns
    them as a :class:`~sb3_dipper.common.hierarchical_policy.HierarchicalPolicy` that acts without the algorithm.

    :param policy: the higher-level policy (class or alias)
    :param env: a goal env (Dict observations with ``observation``, ``achieved_goal``, ``desired_goal``)
    :param learning_rate: learning rate of the higher level
    :param option_steps: K, the primitive steps per option (subgoal)
    :param subgoal_space: the subgoal space (default: the env's declared one, see ``resolve_subgoal_space``)
    :param buffer_size: lower-level replay buffer size (primitive transitions)
    :param learning_starts: primitive steps of uniformly random subgoals and lower actions before learning
    :param batch_size: lower-level minibatch size
    :param tau: lower-level target smoothing coefficient
    :param gamma: lower-level discount factor
    :param train_freq: train the lower level every ``train_freq`` primitive vec-env steps
    :param gradient_steps: lower-level gradient steps per training round
    :param ent_coef: lower-level SAC entropy coefficient (``"auto"`` learns it)
    :param replay_buffer_kwargs: lower ``HerReplayBuffer`` kwargs (``n_sampled_goal``, ``goal_selection_strategy``)
    :param low_learning_rate: learning rate of the lower SAC
    :param low_policy_kwargs: ``policy_kwargs`` of the lower SAC (for example ``net_arch``)
    :param low_level_kwargs: any other keyword argument of the lower ``SAC`` (one that a parameter here sets, such as
        ``buffer_size``, is refused, naming that parameter)
    :param random_subgoal_prob: probability that a subgoal is drawn uniformly at random during training
    :param demo_kwargs: the lower level's Q-filtered behaviour cloning of demonstrations (see
        :mod:`sb3_dipper.common.imitation`; default: none), a dict with the keys

        * ``demo_path``: an npz file, a Minari dataset directory, ``"auto"`` for the task's single default scripted
          demonstration or ``"auto:dart<N>"`` for N DART episodes of its scripted expert (beyond the paper;
          :func:`~sb3_dipper.common.demonstrations.demonstrations_for`); ``None`` (default): no cloning
        * ``n_demos``: how many demonstration episodes to use, from the first (default: all N of ``"auto:dart<N>"``,
          the one of ``"auto"``, the first episode of a file or dataset)
        * ``demo_share``: fraction of each lower batch drawn from the demonstrations (default 0.125)
        * ``bc_coef``: weight of the behaviour-cloning loss (PIPER's lambda_2; default 0.0078)
        * ``rl_coef``: weight of SAC's actor loss while cloning (PIPER's lambda_1; default 1e-3)
        * ``q_filter``: clone only demo actions the lower critic values above the policy's (default ``True``)
        * ``normalize_from_demos``: scale observations by the demonstrations' states (their mean and std + 0.01),
          fixed, instead of the ``VecNormalize`` running statistics of the visited states (beyond the paper; needs
          ``demo_path`` and an env wrapped in ``VecNormalize(norm_obs=True)``; see
          :func:`~sb3_dipper.common.demonstrations.normalize_like_demonstrations`; default ``False``)

        For example ``dict(demo_path="auto", bc_coef=0.02)``. The seven were parameters of their own before, and are
        still taken by their names, with a ``DeprecationWarning``
    :param greedy_episode_prob: probability that an env's training episode is collected with the lower level acting
        greedily (its deterministic action, as in evaluation) while the higher level explores as usual; drawn per env
        at each episode's start (beyond the paper: HAC's subgoal testing per episode; 0: every episode explores)
    :param max_episode_steps: base-env episode length (default: read from the env's ``TimeLimit``)
    :param policy_kwargs: keyword arguments of the higher-level policy
    :param stats_window_size: window of the rollout statistics
    :param tensorboard_log: tensorboard log folder
    :param verbose: 0 silent, 1 info, 2 debug
    :param seed: random seed
    :param device: torch device
    :param _init_setup_model: whether to build the networks at construction
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {}
    lower: DemoSAC
    low_level: SACLowLevel
    option_env: OptionVecEnv | None
    # The lower SAC's update count, saved with the model because the lower SAC is rebuilt on load: its logged count and
    # DIPPER's value-snapshot schedule resume where they were.
    _lower_n_updates: int = 0
    # The lower level's demonstration settings, each of which was a parameter (and is taken by its name, deprecated).
    deprecated_parameters: ClassVar[Mapping[str, MovedParameter]] = {
        name: MovedParameter("demo_kwargs", name) for name in DEFAULT_DEMO_KWARGS
    }
    # The settings checked and completed with their defaults (a model saved before a setting existed loads with it).
    demo_kwargs: dict[str, Any]
    # Models saved before this setting existed load with its default.
    greedy_episode_prob: float = 0.0
    # Whether the subgoal space is the one the env declared (no subgoal_space given): then an env the model is loaded
    # onto, or given with set_env, must declare the same. Models saved before this was recorded are checked too.
    subgoal_space_from_env: bool = True

    def __init__(
        self,
        policy: str | type[BasePolicy],
        env: GymEnv | str | None,
        learning_rate: float | Schedule = 3e-4,
        option_steps: int = 15,
        subgoal_space: SubgoalSpace | None = None,
        buffer_size: int = 1_000_000,
        learning_starts: int = 3000,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.95,
        train_freq: int = 1,
        gradient_steps: int = 1,
        ent_coef: str | float = "auto",
        replay_buffer_kwargs: dict[str, Any] | None = None,
        low_learning_rate: float | Schedule = 1e-3,
        low_policy_kwargs: dict[str, Any] | None = None,
        low_level_kwargs: dict[str, Any] | None = None,
        random_subgoal_prob: float = 0.0,
        demo_kwargs: dict[str, Any] | None = None,
        greedy_episode_prob: float = 0.0,
        max_episode_steps: int | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
    ) -> None:
        policy, env = policy_class_and_goal_env(self, policy, env, verbose)
        super().__init__(
            policy,
            env,
            learning_rate,
            # Copies of every dict given: SB3's SACs add their own keys (use_sde) to the dicts they are handed, and a
            # caller may pass the same dict to another model.
            policy_kwargs=dict(policy_kwargs or {}),
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            support_multi_env=True,
            seed=seed,
            supported_action_spaces=(spaces.Box,),
        )
        self.option_steps = option_steps
        self.subgoal_space = subgoal_space
        self.subgoal_space_from_env = subgoal_space is None
        self.buffer_size = buffer_size
        self.learning_starts = learning_starts
        self.batch_size = batch_size
        self.tau = tau
        self.gamma = gamma
        self.train_freq = train_freq
        self.gradient_steps = gradient_steps
        self.ent_coef = ent_coef
        self.replay_buffer_kwargs = dict(replay_buffer_kwargs or {})
        self.low_learning_rate = low_learning_rate
        self.low_policy_kwargs = dict(low_policy_kwargs or {})
        self.low_level_kwargs = dict(low_level_kwargs or {})
        self.random_subgoal_prob = random_subgoal_prob
        self.demo_kwargs = dict(demo_kwargs or {})
        self.greedy_episode_prob = greedy_episode_prob
        self.max_episode_steps = max_episode_steps
        self.low_normalizer: SubgoalNormalizer | None = None
        self._low_steps_since_train = 0
        self._rng = np.random.default_rng(seed)

    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfHierarchicalAlgorithm],
        path: str | pathlib.Path | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        **kwargs: Any,
    ) -> SelfHierarchicalAlgorithm:
        """:meth:`CheckedLoading.load`; ``subgoal_space=`` replaces the saved subgoal space with the one given, which,
        as one given to the constructor, no env's declared space has to match."""
        if kwargs.get("subgoal_space") is not None:
            kwargs["subgoal_space_from_env"] = False
        return super().load(path, env, device, custom_objects, print_system_info, force_reset, **kwargs)  # type: ignore[return-value]

    # ---------------------------------------------------------------------------------------------------- set-up

    def _check_settings(self) -> None:
        super()._check_settings()
        # Settings may arrive as floats or strings (zoo -params, YAML 5e4): coerce or refuse them here, not in training.
        self.option_steps = as_int("option_steps", self.option_steps, 1)
        self.buffer_size = as_int("buffer_size", self.buffer_size, 1)
        self.learning_starts = as_int("learning_starts", self.learning_starts, 0)
        self.batch_size = as_int("batch_size", self.batch_size, 1)
        self.train_freq = as_int("train_freq", self.train_freq, 1, "the lower level trains every train_freq primitive steps")
        self.gradient_steps = as_int("gradient_steps", self.gradient_steps, 0)
        self.max_episode_steps = as_optional_int(
            "max_episode_steps", self.max_episode_steps, 1, "None reads the env's time limit"
        )
        self.tau = as_float("tau", self.tau, 0.0, 1.0, low_open=True)
        self.gamma = as_float("gamma", self.gamma, 0.0, 1.0, low_open=True)
        self.random_subgoal_prob = as_float("random_subgoal_prob", self.random_subgoal_prob, 0.0, 1.0)
        self.greedy_episode_prob = as_float("greedy_episode_prob", self.greedy_episode_prob, 0.0, 1.0)
        self.low_learning_rate = as_learning_rate("low_learning_rate", self.low_learning_rate)
        self.ent_coef = as_entropy_coefficient("ent_coef", self.ent_coef)
        self.replay_buffer_kwargs = checked_her_kwargs("replay_buffer_kwargs", self.replay_buffer_kwargs)
        check_low_level_kwargs(self.low_level_kwargs)
        self.demo_kwargs = checked_demo_kwargs(self.demo_kwargs)

    def _setup_model(self) -> None:
        self._check_settings()
        self._setup_lr_schedule()
        self.set_random_seed(self.seed)
        if self.env is not None:
            self._check_env_subgoal_space(self.env)
            self.subgoal_space = resolve_subgoal_space(self.env, self.subgoal_space)
            self.max_episode_steps = self.max_episode_steps or self._episode_length(self.env)
            self._warn_if_options_outlast_episodes()
            EnvGoalReward(self.env, type(self).__name__)
        assert self.subgoal_space is not None, "a saved model always carries its subgoal space"
        check_subgoal_space(self.subgoal_space, self.observation_space)
        cloning = self.demo_kwargs["demo_path"] is not None
        demonstrations = self._load_demonstrations() if cloning and self.env is not None else None
        if demonstrations is not None and self.demo_kwargs["normalize_from_demos"]:
            self._normalize_like(demonstrations)
        if self._vec_normalize_env is not None and self.low_normalizer is None:
            self.low_normalizer = SubgoalNormalizer(self.subgoal_space)
            self.low_normalizer.refresh(self._vec_normalize_env)
        self._setup_low_level(demonstrations)
        self._setup_high_level()
        # Which envs' last training subgoal was drawn uniformly at random (the warm-up's, or a random_subgoal_prob swap).
        self.last_random_subgoals = np.zeros(self.n_envs, dtype=bool)
        self.option_env = None
        if self.env is not None:
            self.option_env = OptionVecEnv(
                self.env, self.subgoal_space, self.option_steps, self.low_level, sink=self._on_primitive_step
            )

    def _check_env_subgoal_space(self, env: VecEnv) -> None:
        """Refuse an env that declares another subgoal space than the one the model took from its env.

        A model's higher level proposes subgoals in its own box; on an env with another one (a model of a larger maze
        on a smaller maze with the same observation and action spaces) it would train and act in the old box without
        a word. A box given by the user (``subgoal_space=``) is the user's choice and is not checked.
        """
        if self.subgoal_space is None or not self.subgoal_space_from_env:
            return
        declared = self._env_declared_subgoal_space()
        env_space = resolve_subgoal_space(env)
        if declared.same_as(env_space):
            return
        algorithm = type(self).__name__
        raise ValueError(
            f"The env declares the subgoal space {env_space.describe()}, but this {algorithm} model's is "
            f"{declared.describe()} (the space of the env it was built on): its higher level would propose subgoals "
            f"in that box. Use the model on an env with its subgoal space, or choose the box on purpose when loading: "
            f"{algorithm}.load(path, env=env, subgoal_space=...) keeps the space given (the env's own is "
            "sb3_dipper.common.subgoals.resolve_subgoal_space(env))."
        )

    def _env_declared_subgoal_space(self) -> SubgoalSpace:
        """The part of the model's subgoal space that an env declares, to compare with another env's: all of it."""
        assert self.subgoal_space is not None
        return self.subgoal_space

    def _warn_if_options_outlast_episodes(self) -> None:
        """Allowed but rarely meant: every option is cut short by the episode's end, so the higher level acts once per
        episode and the hierarchy never chains options."""
        if self.max_episode_steps is not None and self.option_steps > self.max_episode_steps:
            warnings.warn(
                f"option_steps={self.option_steps} is longer than the episode (max_episode_steps={self.max_episode_steps}):"
                f" every option ends with the episode, so {type(self).__name__}'s higher level acts once per episode. "
                f"Use option_steps < {self.max_episode_steps} for several options per episode."
            )

    @staticmethod
    def _episode_length(env: VecEnv) -> int:
        spec = env.get_attr("spec", indices=[0])[0]
        length = getattr(spec, "max_episode_steps", None)
        if length is None:
            raise ValueError(
                "The env has no time limit (spec.max_episode_steps is None): hierarchical algorithms need the "
                "episode length to size higher-level trajectories. Pass max_episode_steps=... or wrap it in TimeLimit."
            )
        return int(length)

    @property
    def high_steps(self) -> int:
        """T, the most higher-level decisions in one base episode."""
        assert self.max_episode_steps is not None
        return math.ceil(self.max_episode_steps / self.option_steps)

    def _higher_level_trajectory_buffer(self, capacity: int) -> TrajectoryBuffer:
        """A store of ``capacity`` whole higher-level trajectories: :attr:`high_steps` options of subgoal actions."""
        assert self.subgoal_space is not None
        return TrajectoryBuffer(
            capacity,
            self.high_steps,
            self.observation_space,  # type: ignore[arg-type]
            self.subgoal_space.dim,
            self.n_envs,
        )

    @staticmethod
    def _normalizable(vec_normalize: VecNormalize | None) -> VecNormalize:
        """``vec_normalize``, or the error ``normalize_from_demos`` gives for an env without observation statistics."""
        if vec_normalize is None or not vec_normalize.norm_obs:
            raise ValueError(
                "demo_kwargs['normalize_from_demos']=True sets the observation statistics of the env's VecNormalize, "
                "but the env is not wrapped in VecNormalize(norm_obs=True): wrap it (the zoo's normalize: true) or "
                "leave normalize_from_demos out of demo_kwargs"
            )
        return vec_normalize

    def _normalize_like(self, demonstrations: Demonstrations) -> None:
        """``normalize_from_demos``: fix the env's ``VecNormalize`` statistics to the demonstrations' states."""
        normalize_like_demonstrations(self._normalizable(self._vec_normalize_env), demonstrations)
        self._refresh_low_normalizer()

    def _setup_low_level(self, demonstrations: Demonstrations | None = None) -> None:
        """The lower SAC, cloning ``demonstrations`` (the first ``n_demos`` of ``demo_path``) when given."""
        assert self.subgoal_space is not None
        low_env = SubgoalVecEnv(
            low_level_observation_space(self.observation_space, self.subgoal_space),  # type: ignore[arg-type]
            self.action_space,
            self.subgoal_space,
            self.n_envs,
        )
        buffer_size = self.buffer_size if self.env is not None else PREDICT_ONLY_BUFFER_SIZE * self.n_envs
        self.lower = DemoSAC(
            "MultiInputPolicy",
            low_env,
            learning_rate=self.low_learning_rate,
            buffer_size=buffer_size,
            learning_starts=0,
            batch_size=self.batch_size,
            tau=self.tau,
            gamma=self.gamma,
            train_freq=self.train_freq,
            gradient_steps=self.gradient_steps,
            ent_coef=self.ent_coef,
            replay_buffer_class=HerReplayBuffer,
            replay_buffer_kwargs=dict(self.replay_buffer_kwargs),
            policy_kwargs=dict(self.low_policy_kwargs),
            device=self.device,
            demo_share=self.demo_kwargs["demo_share"],
            bc_coef=self.demo_kwargs["bc_coef"],
            rl_coef=self.demo_kwargs["rl_coef"],
            q_filter=self.demo_kwargs["q_filter"],
            **self.low_level_kwargs,
        )
        self.lower._n_updates = self._lower_n_updates
        if demonstrations is not None:
            self.lower.demonstrations = self._demonstration_buffer(demonstrations)
        self.lower._vec_normalize_env = self.low_normalizer  # type: ignore[assignment]
        self.low_level = SACLowLevel(self.lower, self.low_normalizer)

    def _load_demonstrations(self) -> Demonstrations:
        """The first ``n_demos`` episodes of ``demo_path``, checked against the env's spaces."""
        demo_path = self.demo_kwargs["demo_path"]
        assert self.env is not None and demo_path is not None
        demonstrations = demonstrations_for(demo_path, self.env, self.demo_kwargs["n_demos"])
        # Checked here, at construction: a mismatch would otherwise surface at the first update as a tensor-size error.
        demonstrations.check_spaces(self.observation_space, self.action_space)
        return demonstrations

    def _demonstration_buffer(self, demonstrations: Demonstrations) -> DemonstrationBuffer:
        assert self.subgoal_space is not None and isinstance(self.action_space, spaces.Box)
        actions = np.clip(demonstrations.actions, self.action_space.low, self.action_space.high)
        scaled_actions = self.lower.policy.scale_action(actions)
        return DemonstrationBuffer(demonstrations, self.subgoal_space, scaled_actions)

    @abstractmethod
    def _setup_high_level(self) -> None:
        """Build the higher level (policy, buffers, optimizers)."""

    # ---------------------------------------------------------------------------------------------------- acting

    @abstractmethod
    def _high_level_actions(self, observation: DictObs, deterministic: bool) -> np.ndarray:
        """Higher-level actions in [-1, 1]^d for a batch of (normalised) observations."""

    def _subgoal_actions(self, goals: np.ndarray, key: str = "desired_goal") -> np.ndarray:
        """The higher-level actions whose subgoals are ``goals``, given as the (normalised) observations give them.

        :param key: the observation's key that holds ``goals`` (``"achieved_goal"`` for where the agent is)
        """
        assert self.subgoal_space is not None
        if self.low_normalizer is not None:
            goals = self.low_normalizer.unnormalize_goal(goals, key)
        return self.subgoal_space.to_unit(self.subgoal_space.project(goals))

    def _collecting_high_level_actions(self, observation: DictObs) -> np.ndarray:
        """The higher level's own proposals while collecting (what :meth:`predict` proposes, sampled)."""
        return self._high_level_actions(observation, deterministic=False)

    def _predict_plans(self) -> bool:
        """Whether :meth:`predict` uses state that :meth:`export_policy` cannot export (a planner's graph)."""
        return False

    def _training_high_level_actions(self, observation: DictObs) -> np.ndarray:
        """Actions while collecting: uniform before ``learning_starts`` and with ``random_subgoal_prob`` (those rows are
        :attr:`last_random_subgoals`)."""
        assert self.subgoal_space is not None
        shape = (self.n_envs, self.subgoal_space.dim)
        if self.num_timesteps < self.learning_starts:
            self.last_random_subgoals = np.ones(self.n_envs, dtype=bool)
            return self._rng.uniform(-1.0, 1.0, size=shape).astype(np.float32)
        actions = self._collecting_high_level_actions(observation)
        random = self._rng.random(self.n_envs) < self.random_subgoal_prob
        actions[random] = self._rng.uniform(-1.0, 1.0, size=(int(random.sum()), shape[1]))
        self.last_random_subgoals = random
        return actions

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """A primitive action; ``state = (subgoals, steps_left)`` carries the current option between calls.

        ``observation`` is what the (possibly ``VecNormalize``-d) env returns, batched or not. Both levels act with their
        policies (never the random actions of the warm-up), as the policy :meth:`export_policy` returns does.
        """
        self._refresh_low_normalizer()
        self.policy.set_training_mode(False)
        return self._hierarchical_policy(self._high_level_actions, self._acting_low_level()).predict(
            observation, state, episode_start, deterministic
        )

    def export_policy(self) -> HierarchicalPolicy:
        """Both levels as a :class:`~sb3_dipper.common.hierarchical_policy.HierarchicalPolicy` that acts without the
        algorithm: copies of the higher and lower policies, the subgoal space, ``option_steps`` and the lower level's
        ``VecNormalize`` statistics. Its ``predict(obs, state, episode_start, deterministic)`` gives this model's
        actions; later training does not change it.

        :raises NotImplementedError: for a model whose :meth:`predict` plans (DIPPER with a planner, unless its
            ``in_predict`` is ``False``): its waypoints come from the subgoal graph, which is not exported; use
            :meth:`predict`
        """
        if self._predict_plans():
            raise NotImplementedError(
                f"This {type(self).__name__} plans over its subgoal graph, which export_policy does not export: "
                "act with model.predict, export a model trained without a planner, or (planner mode 'subgoal') set "
                "model.planner.in_predict = False to export the preference-trained policy alone"
            )
        self._refresh_low_normalizer()
        policy = self._hierarchical_policy(PolicyHighLevel(self.policy), self._acting_low_level())
        return copy.deepcopy(policy)

    def _hierarchical_policy(self, high_level: HighLevelActions, low_level: ActingLowLevel) -> HierarchicalPolicy:
        assert self.subgoal_space is not None
        return HierarchicalPolicy(
            high_level,
            low_level,
            self.subgoal_space,
            self.option_steps,
            self.observation_space,  # type: ignore[arg-type]
            self.action_space,  # type: ignore[arg-type]
            self.low_normalizer,
        )

    def _acting_low_level(self) -> ActingLowLevel:
        """The lower level as it acts outside training: its SAC policy alone."""
        return SACPolicyLowLevel(self.lower.policy)

    # ---------------------------------------------------------------------------------------------------- learning

    def learn(
        self: SelfHierarchicalAlgorithm,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "run",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfHierarchicalAlgorithm:
        """Train for ``total_timesteps`` primitive env steps (SB3's ``learn``).

        Each iteration collects one *rollout*, one option of every env (``on_rollout_start``, an ``on_step`` per
        primitive step, ``on_rollout_end``), then runs one training round once ``learning_starts`` steps are done.
        ``reset_num_timesteps=False`` continues the count and the env's episodes where the last call stopped.
        """
        if self.option_env is None:
            name = type(self).__name__
            raise ValueError(
                f"learn() needs an env: pass one to {name}(...), to {name}.load(path, env=...) or to model.set_env(env)"
            )
        total_timesteps, callback = self._setup_learn(
            total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar
        )
        self.option_env.observe_reset(self._last_obs)  # type: ignore[arg-type]
        self.lower.set_logger(LevelLogger(self.logger, "low"))  # type: ignore[arg-type]
        self._log_interval = log_interval
        self._callback = callback
        callback.on_training_start(locals(), globals())
        while self.num_timesteps < total_timesteps:
            if not self._collect_option():
                break
            if self.num_timesteps >= self.learning_starts and self._has_training_data():
                self.train()
        self._refresh_low_normalizer()
        callback.on_training_end()
        return self

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> tuple[int, BaseCallback]:
        if reset_num_timesteps or self._last_obs is None:
            # The env is about to be reset: an option a callback interrupted must not run on into the new episode.
            self._end_open_episodes()
        self._option_metrics: dict[str, deque] = {
            key: deque(maxlen=self._stats_window_size) for key in self._option_metric_keys()
        }
        return super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)

    def _option_metric_keys(self) -> tuple[str, ...]:
        """The ``rollout/<key>`` averages over the last options that :meth:`dump_logs` logs (a subclass adds its own)."""
        return ("subgoal_distance", "low_value")

    def _refresh_low_normalizer(self) -> None:
        """Copy the live ``VecNormalize`` statistics (a saved model keeps the last copy for ``load(env=None)``)."""
        if self.low_normalizer is not None and self._vec_normalize_env is not None:
            self.low_normalizer.refresh(self._vec_normalize_env)

    def _end_open_episodes(self) -> None:
        """Close what an interrupted option left open; a subclass also closes its higher-level episodes."""
        buffer = self.lower.replay_buffer
        if isinstance(buffer, HerReplayBuffer) and (buffer._current_ep_start != buffer.pos).any():
            buffer.truncate_last_trajectory()

    def _collect_option(self) -> bool:
        """One rollout: one option of every env, stored; return False when a callback stopped training."""
        assert self.option_env is not None and self._last_obs is not None
        self.policy.set_training_mode(False)
        self.low_level.random_actions = self.num_timesteps < self.learning_starts
        if self.greedy_episode_prob > 0.0 and self.low_level.greedy is None:  # the first episodes (or after a load)
            self._draw_greedy_episodes(np.ones(self.n_envs, dtype=bool))
        self._refresh_low_normalizer()
        self._callback.on_rollout_start()
        start_obs = {key: value.copy() for key, value in self.option_env.original_obs.items()}  # type: ignore[union-attr]
        high_actions = self._training_high_level_actions(self._last_obs)  # type: ignore[arg-type]
        self._continue_training = True
        new_obs, rewards, dones, infos = self.option_env.step(high_actions)
        # An option a callback stopped is stored like any shortened option, and _last_obs follows the env, so that
        # learn(..., reset_num_timesteps=False) resumes from where the env is.
        self._store_option(start_obs, high_actions, new_obs, rewards, dones, infos)  # type: ignore[arg-type]
        for info in infos:
            self._option_metrics["subgoal_distance"].append(info["subgoal_distance"])
            if "low_value" in info and self.num_timesteps >= self.learning_starts:
                self._option_metrics["low_value"].append(info["low_value"])
        self._last_obs = new_obs  # type: ignore[assignment]
        if not self._continue_training:
            # As SB3's collect_rollouts: no on_rollout_end after a callback stopped training.
            return False
        self._callback.on_rollout_end()
        return True

    @abstractmethod
    def _store_option(
        self,
        start_obs: DictObs,
        high_actions: np.ndarray,
        new_obs: DictObs,
        rewards: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """Store a finished option of every env (``start_obs`` original, ``new_obs`` as the env returned it)."""

    def _on_primitive_step(self, transition: PrimitiveTransition) -> bool:
        """The option layer's sink: count the step, run callbacks, fill the lower buffer, log episodes."""
        self.num_timesteps += self.n_envs
        self._low_steps_since_train += 1
        if self.num_timesteps <= self.learning_starts:
            # As in SB3's SAC, the warm-up owes no lower updates: only windows of train_freq steps (counted from the
            # start, as SB3's rollouts) that end after learning_starts do, so the first round does not catch up on them.
            self._low_steps_since_train %= self.train_freq
        dones, infos = transition.base_dones, transition.infos
        self._callback.update_locals(locals())
        if not self._callback.on_step():
            self._continue_training = False
            # The option ends at this step, so its lower segment does too: no HER episode spans two subgoals.
            transition.segment_ends = np.ones_like(transition.segment_ends)
        self.low_level.store(transition)
        self._draw_greedy_episodes(dones)
        self._update_info_buffer(infos, dones)
        self._update_current_progress_remaining(self.num_timesteps, self._total_timesteps)
        for _ in range(int(np.sum(dones))):
            self._episode_num += 1
            if self._log_interval is not None and self._episode_num % self._log_interval == 0:
                self.dump_logs()
        return self._continue_training

    def _draw_greedy_episodes(self, starting: np.ndarray) -> None:
        """``greedy_episode_prob``: whether the envs of the mask ``starting`` collect their next episode greedily."""
        if self.greedy_episode_prob == 0.0:  # a scripted lower level (RAPS's) has no greedy flags to keep
            return
        self.low_level.greedy = self._drawn_episode_flags(self.low_level.greedy, starting, self.greedy_episode_prob)

    def _drawn_episode_flags(self, flags: np.ndarray | None, starting: np.ndarray, probability: float) -> np.ndarray | None:
        """Per env, whether its episode takes a switch drawn once per episode with ``probability``: ``flags`` (all
        ``False`` where ``None``) with the envs of the mask ``starting`` drawn anew. At probability 0 nothing is drawn,
        so the random stream stays that of a run without the switch."""
        if probability == 0.0:
            return flags
        if flags is None:
            flags = np.zeros(self.n_envs, dtype=bool)
        starting = np.asarray(starting, dtype=bool)  # a mask, also where a VecEnv reports dones as numbers
        flags[starting] = self._rng.random(int(starting.sum())) < probability
        return flags

    def _has_training_data(self) -> bool:
        """Whether the buffers can be sampled (a model resumed without its buffers must first collect some)."""
        return has_finished_episode(self.lower.replay_buffer)

    def _train_low_level(self) -> None:
        """The lower SAC's updates owed for the primitive steps collected since the last round."""
        gradient_steps = (self._low_steps_since_train // self.train_freq) * self.gradient_steps
        self._low_steps_since_train %= self.train_freq
        if gradient_steps > 0:
            self.lower._current_progress_remaining = self._current_progress_remaining
            self.lower.train(gradient_steps=gradient_steps, batch_size=self.batch_size)
            self._lower_n_updates = self.lower._n_updates

    @abstractmethod
    def train(self) -> None:
        """One training round after an option: the lower level's owed updates, then the higher level's."""

    def dump_logs(self) -> None:
        """SB3's off-policy log keys (``rollout/success_rate``, ``time/fps``, ...) plus the option metrics."""
        assert self.ep_info_buffer is not None and self.ep_success_buffer is not None
        time_elapsed = max((time.time_ns() - self.start_time) / 1e9, sys.float_info.epsilon)
        fps = int((self.num_timesteps - self._num_timesteps_at_start) / time_elapsed)
        self.logger.record("time/episodes", self._episode_num, exclude="tensorboard")
        if len(self.ep_info_buffer) > 0 and len(self.ep_info_buffer[0]) > 0:
            self.logger.record("rollout/ep_rew_mean", safe_mean([ep_info["r"] for ep_info in self.ep_info_buffer]))
            self.logger.record("rollout/ep_len_mean", safe_mean([ep_info["l"] for ep_info in self.ep_info_buffer]))
        if len(self.ep_success_buffer) > 0:
            self.logger.record("rollout/success_rate", safe_mean(self.ep_success_buffer))
        for key, values in self._option_metrics.items():
            if len(values) > 0:
                self.logger.record(f"rollout/{key}", safe_mean(values))
        if isinstance(self.lower, SAC):  # a learned lower level (RAPS's primitives are scripted)
            for network, share in sac_dead_units(self.lower, self.low_normalizer).items():
                self.logger.record(f"train/low_{network}_dead_units", share)
        self.logger.record("time/fps", fps)
        self.logger.record("time/time_elapsed", int(time_elapsed), exclude="tensorboard")
        self.logger.record("time/total_timesteps", self.num_timesteps, exclude="tensorboard")
        self.logger.dump(step=self.num_timesteps)

    # ---------------------------------------------------------------------------------------------------- saving

    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(),
            "low_level",
            "option_env",
            "_callback",
            "_option_metrics",
            "last_random_subgoals",
        ]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        return sac_torch_save_params(self.lower, "lower")

    @unchanged_on_failure
    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        """SB3's ``set_env`` (same spaces, number of envs and time limit): the next ``learn`` runs on ``env``.

        A model loaded without an env holds predict-only buffers and no option layer: it is rebuilt for ``env``
        around its networks, optimizers and counters, with its configured ``buffer_size`` (load saved buffers with
        ``load_replay_buffer`` after ``set_env``). A model that has an env keeps its replay data, as in SB3, and its
        option layer moves to ``env``.
        """
        # Refused before anything changes.
        if self.demo_kwargs["normalize_from_demos"]:
            self._normalizable(unwrap_vec_normalize(env) if isinstance(env, VecEnv) else None)
        env = self._wrap_env(env, self.verbose)
        check_for_correct_spaces(env, self.observation_space, self.action_space)
        self._check_env_subgoal_space(env)
        super().set_env(env, force_reset)
        if self.option_env is None:
            self._rebuild_keeping_parameters()
        else:
            assert self.env is not None and self.subgoal_space is not None
            if self.demo_kwargs["normalize_from_demos"]:
                self._normalize_like(self._load_demonstrations())
            self.option_env = OptionVecEnv(
                self.env, self.subgoal_space, self.option_steps, self.option_env.low_level, sink=self.option_env.sink
            )

    @property
    def replay_buffer(self) -> ReplayBuffer | None:
        """The lower replay buffer (so that ``CheckpointCallback(save_replay_buffer=True)`` saves the buffers)."""
        return self.lower.replay_buffer

    def save_replay_buffer(self, path: Any) -> None:
        """Save the lower replay buffer (SB3's pickle at ``path``) and the higher level's data in files beside it.

        Each file is written under a temporary name and renamed into place, so a run killed while saving leaves every
        file either complete or absent. Streams are refused (a ``TypeError``): the files beside need a name.
        """
        lower_path = replay_buffer_path(path, f"{type(self).__name__}.save_replay_buffer", reading=False)
        save_replay_buffer_file(lower_path, self.lower.replay_buffer)
        self._save_high_level_data(str(lower_path))

    def load_replay_buffer(self, path: Any, truncate_last_traj: bool = True) -> None:
        """Load what :meth:`save_replay_buffer` wrote, to resume training where it stopped.

        All or nothing: every file is read and checked against the model before any buffer is replaced, so on an error
        (naming the file) the model keeps the buffers it had.
        """
        lower_path = replay_buffer_path(path, f"{type(self).__name__}.load_replay_buffer", reading=True)
        lower_buffer = read_replay_buffer(lower_path, self.lower, truncate_last_traj)
        install_high_level_data = self._load_high_level_data(str(lower_path), truncate_last_traj)
        self.lower.replay_buffer = lower_buffer
        install_high_level_data()

    @abstractmethod
    def _save_high_level_data(self, path: str) -> None:
        """Save the higher level's replay data next to the lower buffer saved at ``path`` (each file atomically)."""

    @abstractmethod
    def _load_high_level_data(self, path: str, truncate_last_traj: bool) -> Callable[[], None]:
        """Read and check what :meth:`_save_high_level_data` wrote, changing nothing; return what installs it.

        The returned step only assigns what was read, so it cannot fail half-way.
        """


# The lower SAC's settings that the hierarchy gives it itself, and the parameter of the hierarchy that sets each.
LOWER_SAC_SETTINGS = {
    "policy": "low_policy_kwargs (the lower policy is SB3's MultiInputPolicy)",
    "env": "the hierarchy's env",
    "learning_rate": "low_learning_rate",
    "buffer_size": "buffer_size",
    "learning_starts": "learning_starts (the hierarchy's: the lower level trains from then on)",
    "batch_size": "batch_size",
    "tau": "tau",
    "gamma": "gamma",
    "train_freq": "train_freq",
    "gradient_steps": "gradient_steps",
    "ent_coef": "ent_coef",
    "replay_buffer_class": "replay_buffer_kwargs (the lower buffer is SB3's HerReplayBuffer)",
    "replay_buffer_kwargs": "replay_buffer_kwargs",
    "policy_kwargs": "low_policy_kwargs",
    "device": "device",
    "demo_share": "demo_kwargs['demo_share']",
    "bc_coef": "demo_kwargs['bc_coef']",
    "rl_coef": "demo_kwargs['rl_coef']",
    "q_filter": "demo_kwargs['q_filter']",
    "demonstrations": "demo_kwargs['demo_path']",
}


def check_low_level_kwargs(low_level_kwargs: Mapping[str, Any]) -> None:
    """Refuse a key of ``low_level_kwargs`` that the hierarchy sets itself (naming the parameter that does) or that
    neither SB3's SAC nor the lower level's cloning (``target_q_bounds``) takes (naming the closest)."""
    for key in low_level_kwargs:
        if key in LOWER_SAC_SETTINGS:
            raise InvalidSetting(
                "low_level_kwargs", f"low_level_kwargs[{key!r}] is set by the hierarchy: use {LOWER_SAC_SETTINGS[key]}"
            )
    sac_settings = {key: value for key, value in low_level_kwargs.items() if key != "target_q_bounds"}
    check_keyword_arguments(SAC, sac_settings, "low_level_kwargs")


def has_finished_episode(buffer: ReplayBuffer | None) -> bool:
    """Whether a HER buffer holds a finished episode (before that, SB3's HER cannot sample)."""
    return isinstance(buffer, HerReplayBuffer) and bool(buffer.ep_length.any())


def sibling_path(path: str, suffix: str) -> str:
    """``replay_buffer.pkl`` -> ``replay_buffer<suffix>``: where the higher level's data sits beside the lower buffer."""
    return f"{path.removesuffix('.pkl')}{suffix}"
