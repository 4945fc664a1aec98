"""HIER: vanilla two-level SAC with HER at both levels, the DIPPER paper's plain hierarchical baseline.

The higher level is an SB3 ``SAC`` over subgoals in ``[-1, 1]^d`` whose reward is the environment's sparse reward at
the end of each option, with ``HerReplayBuffer`` relabelling final goals; the lower level is the shared SAC+HER on
subgoals. Its higher-level transitions depend on the lower level's current behaviour: the non-stationarity DIPPER's
preferences avoid.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices
from stable_baselines3.her.her_replay_buffer import HerReplayBuffer

from sb3_dipper.common.files import read_replay_buffer, save_replay_buffer_file
from sb3_dipper.common.hierarchical import HierarchicalAlgorithm, has_finished_episode, sibling_path
from sb3_dipper.common.low_level import LevelLogger, sac_torch_save_params
from sb3_dipper.common.option_env import DictObs, LevelVecEnv
from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.common.validation import as_entropy_coefficient, as_float, as_int, checked_her_kwargs
from sb3_dipper.hier.policies import MlpPolicy, MultiInputPolicy

SelfHIER = TypeVar("SelfHIER", bound="HIER")


class OptionGoalVecEnv(LevelVecEnv):
    """The higher level's goal env as SB3 sees it: base observations, unit actions, the base ``compute_reward``.

    Never stepped (the option layer drives the envs); ``compute_reward`` is forwarded to the base env, which HER needs.

    :param observation_space: the base env's observation space
    :param action_space: the higher-level action space
    :param base_env: the base VecEnv (``None`` when the model was loaded only to predict)
    :param num_envs: number of parallel envs
    """

    def __init__(self, observation_space: spaces.Dict, action_space: spaces.Box, base_env: VecEnv | None, num_envs: int):
        super().__init__(observation_space, action_space, num_envs, level="higher")
        self.base_env = base_env

    def env_method(
        self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **method_kwargs: Any
    ) -> list[Any]:
        if self.base_env is None:
            raise RuntimeError("This model was loaded without an env: pass env=... to load() to train it.")
        return self.base_env.env_method(method_name, *method_args, indices=indices, **method_kwargs)


class HIER(HierarchicalAlgorithm):
    """HIER: two-level SAC, HER at both levels (the "HIER" baseline of the DIPPER paper and of the authors' PIPER code).

    The lower-level parameters are those of :class:`~sb3_dipper.common.hierarchical.HierarchicalAlgorithm`; the
    ``high_*`` parameters configure the higher SAC, which trains ``high_gradient_steps`` times per option.

    :param policy: the higher SAC's policy (``"MlpPolicy"`` or ``"MultiInputPolicy"``: SAC's ``MultiInputPolicy``)
    :param env: a goal env
    :param learning_rate: learning rate of the higher SAC
    :param option_steps: K, primitive steps per subgoal
    :param subgoal_space: subgoal space (default: the env's declared one)
    :param high_buffer_size: higher replay buffer size (options)
    :param high_batch_size: higher minibatch size
    :param high_gamma: higher discount factor (per option)
    :param high_tau: higher target smoothing coefficient
    :param high_ent_coef: higher entropy coefficient
    :param high_gradient_steps: higher gradient steps per option
    :param high_replay_buffer_kwargs: higher ``HerReplayBuffer`` kwargs
    :param random_subgoal_prob: probability of a uniformly random subgoal during training
    :param buffer_size: lower replay buffer size
    :param learning_starts: primitive steps of random subgoals and lower actions before learning
    :param batch_size: lower minibatch size
    :param tau: lower target smoothing coefficient
    :param gamma: lower discount factor
    :param train_freq: lower training frequency (primitive vec-env steps)
    :param gradient_steps: lower gradient steps per training round
    :param ent_coef: lower entropy coefficient
    :param replay_buffer_kwargs: lower ``HerReplayBuffer`` kwargs
    :param low_learning_rate: lower learning rate
    :param low_policy_kwargs: lower SAC ``policy_kwargs``
    :param low_level_kwargs: other lower ``SAC`` kwargs (not those set by a parameter here, such as ``buffer_size``)
    :param demo_kwargs: the lower level's behaviour cloning of demonstrations, a dict with the keys ``demo_path``
        (default ``None``: none), ``n_demos``, ``demo_share``, ``bc_coef``, ``rl_coef``, ``q_filter`` and
        ``normalize_from_demos`` (see :class:`~sb3_dipper.common.hierarchical.HierarchicalAlgorithm`), for example
        ``dict(demo_path="auto", bc_coef=0.02)``; each key is also taken as a parameter of its own, deprecated
    :param greedy_episode_prob: probability that an env's training episode is collected with the lower level acting
        greedily (its deterministic action) while the higher level explores (beyond the paper; 0: off)
    :param max_episode_steps: base episode length (default: the env's time limit)
    :param policy_kwargs: higher SAC ``policy_kwargs``
    :param stats_window_size: window of rollout statistics
    :param tensorboard_log: tensorboard folder
    :param verbose: verbosity
    :param seed: random seed
    :param device: torch device
    :param _init_setup_model: build the networks now
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"MlpPolicy": MlpPolicy, "MultiInputPolicy": MultiInputPolicy}
    # Subclasses that change how the higher level learns (PIPER's reward model, SAGA's discriminator) swap this class.
    higher_class: ClassVar[type[SAC]] = SAC
    higher: SAC

    def __init__(
        self,
        policy: str | type[BasePolicy],
        env: GymEnv | str | None,
        learning_rate: float | Schedule = 1e-3,
        option_steps: int = 15,
        subgoal_space: SubgoalSpace | None = None,
        high_buffer_size: int = 100_000,
        high_batch_size: int = 256,
        high_gamma: float = 0.95,
        high_tau: float = 0.005,
        high_ent_coef: str | float = "auto",
        high_gradient_steps: int = 1,
        high_replay_buffer_kwargs: dict[str, Any] | None = None,
        random_subgoal_prob: float = 0.0,
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
        demo_kwargs: dict[str, Any] | None = None,
        greedy_episode_prob: float = 0.0,
        max_episode_steps: int | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        super().__init__(
            policy,
            env,
            learning_rate,
            option_steps=option_steps,
            subgoal_space=subgoal_space,
            buffer_size=buffer_size,
            learning_starts=learning_starts,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            ent_coef=ent_coef,
            replay_buffer_kwargs=replay_buffer_kwargs,
            low_learning_rate=low_learning_rate,
            low_policy_kwargs=low_policy_kwargs,
            low_level_kwargs=low_level_kwargs,
            random_subgoal_prob=random_subgoal_prob,
            demo_kwargs=demo_kwargs,
            greedy_episode_prob=greedy_episode_prob,
            max_episode_steps=max_episode_steps,
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            seed=seed,
            device=device,
        )
        self.high_buffer_size = high_buffer_size
        self.high_batch_size = high_batch_size
        self.high_gamma = high_gamma
        self.high_tau = high_tau
        self.high_ent_coef = high_ent_coef
        self.high_gradient_steps = high_gradient_steps
        self.high_replay_buffer_kwargs = dict(high_replay_buffer_kwargs or {})
        if _init_setup_model:
            self._setup_model()

    def _check_settings(self) -> None:
        super()._check_settings()
        self.high_buffer_size = as_int("high_buffer_size", self.high_buffer_size, 1)
        self.high_batch_size = as_int("high_batch_size", self.high_batch_size, 1)
        self.high_gamma = as_float("high_gamma", self.high_gamma, 0.0, 1.0, low_open=True)
        self.high_tau = as_float("high_tau", self.high_tau, 0.0, 1.0, low_open=True)
        self.high_gradient_steps = as_int("high_gradient_steps", self.high_gradient_steps, 0)
        self.high_ent_coef = as_entropy_coefficient("high_ent_coef", self.high_ent_coef)
        self.high_replay_buffer_kwargs = checked_her_kwargs("high_replay_buffer_kwargs", self.high_replay_buffer_kwargs)

    def _setup_high_level(self) -> None:
        assert self.subgoal_space is not None
        high_env = OptionGoalVecEnv(self.observation_space, self.subgoal_space.unit_box, self.env, self.n_envs)  # type: ignore[arg-type]
        self.higher = self.higher_class(
            self.policy_class,  # type: ignore[arg-type]
            high_env,
            learning_rate=self.learning_rate,
            buffer_size=self.high_buffer_size if self.env is not None else 16 * self.n_envs,
            learning_starts=0,
            batch_size=self.high_batch_size,
            tau=self.high_tau,
            gamma=self.high_gamma,
            ent_coef=self.high_ent_coef,
            replay_buffer_class=HerReplayBuffer,
            # Copies: SB3's SAC adds use_sde to the policy_kwargs it is handed.
            replay_buffer_kwargs=dict(self.high_replay_buffer_kwargs),
            policy_kwargs=dict(self.policy_kwargs),
            device=self.device,
        )
        self.higher._vec_normalize_env = self._vec_normalize_env
        self.policy = self.higher.policy

    def learn(
        self: SelfHIER,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "HIER",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfHIER:
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    def _high_level_actions(self, observation: DictObs, deterministic: bool) -> np.ndarray:
        actions, _ = self.higher.policy.predict(observation, deterministic=deterministic)  # type: ignore[arg-type]
        return np.asarray(actions, dtype=np.float32).reshape(-1, self.higher.action_space.shape[0])  # type: ignore[index]

    def _store_option(
        self,
        start_obs: DictObs,
        high_actions: np.ndarray,
        new_obs: DictObs,
        rewards: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """One higher-level transition per env: (s_t, u_t, r^H = env reward at the option's end, s_{t+K})."""
        assert self.option_env is not None and self.option_env.reached_obs is not None
        reward = self._vec_normalize_env.get_original_reward() if self._vec_normalize_env is not None else rewards
        buffer = self.higher.replay_buffer
        assert isinstance(buffer, HerReplayBuffer)
        buffer.add(start_obs, self.option_env.reached_obs, high_actions, reward, dones, infos)

    def _end_open_episodes(self) -> None:
        super()._end_open_episodes()
        buffer = self.higher.replay_buffer
        if isinstance(buffer, HerReplayBuffer) and (buffer._current_ep_start != buffer.pos).any():
            buffer.truncate_last_trajectory()

    def _has_training_data(self) -> bool:
        return super()._has_training_data() and has_finished_episode(self.higher.replay_buffer)

    def train(self) -> None:
        """The lower SAC's owed updates, then ``high_gradient_steps`` updates of the higher SAC."""
        self._train_low_level()
        self.higher._current_progress_remaining = self._current_progress_remaining
        self.higher.train(gradient_steps=self.high_gradient_steps, batch_size=self.high_batch_size)
        self._n_updates += self.high_gradient_steps

    def _setup_learn(self, *args: Any, **kwargs: Any) -> Any:
        result = super()._setup_learn(*args, **kwargs)
        self.higher.set_logger(LevelLogger(self.logger, "high"))  # type: ignore[arg-type]
        return result

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "higher"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        high_state_dicts, high_variables = sac_torch_save_params(self.higher, "higher")
        return [*high_state_dicts, *state_dicts], [*high_variables, *variables]

    def _save_high_level_data(self, path: str) -> None:
        """The higher replay buffer, SB3's pickle beside the lower one (``x.pkl`` -> ``x.higher.pkl``), atomically."""
        save_replay_buffer_file(sibling_path(path, ".higher.pkl"), self.higher.replay_buffer)

    def _load_high_level_data(self, path: str, truncate_last_traj: bool) -> Callable[[], None]:
        higher_buffer = read_replay_buffer(sibling_path(path, ".higher.pkl"), self.higher, truncate_last_traj)

        def install() -> None:
            self.higher.replay_buffer = higher_buffer

        return install
