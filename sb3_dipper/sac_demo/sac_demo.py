"""SACDemo: the flat SAC+HER baseline with the hierarchies' demonstrations and Q-filtered behaviour cloning.

The DIPPER paper compares its hierarchies, whose lower level clones demonstrations, with a flat SAC+HER that clones
nothing. SACDemo is that flat agent with the lower level's cloning (:class:`~sb3_dipper.common.imitation.DemoSAC`,
the authors' PIPER loss): each batch mixes replay transitions with a ``demo_share`` of demonstration transitions, both
train the critics, and the actor loss is

    rl_coef * SAC's actor loss  +  bc_coef * sum_{demo, Q-filter} ||mu(s) - a_demo||^2

The demonstrations and the cloning settings are those the hierarchies take (``demo_kwargs``: ``demo_path``,
``n_demos``, ``demo_share``, ``bc_coef``, ``rl_coef``, ``q_filter``), the demonstrations relabelled as theirs are (with
probability 0.8 the goal of a demo step is the goal achieved after a uniformly drawn later step of its episode,
otherwise the demonstration's own goal), with the env's own goals and reward where a lower level has subgoals
(:class:`~sb3_dipper.common.imitation.EnvGoals`). A comparison row of SACDemo against SAC+HER shows what the
demonstrations give a flat agent; against a hierarchy with the same ``demo_kwargs``, what the hierarchy gives.

Without ``demo_kwargs["demo_path"]`` SACDemo trains as SB3's ``SAC``.
"""

from __future__ import annotations

from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import HerReplayBuffer
from stable_baselines3.common.buffers import DictReplayBuffer, ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule

from sb3_dipper.common.demonstrations import demonstrations_for
from sb3_dipper.common.hierarchical import has_finished_episode
from sb3_dipper.common.imitation import DEFAULT_DEMO_KWARGS, DemonstrationBuffer, DemoSAC, EnvGoals, checked_demo_kwargs
from sb3_dipper.common.loading import CheckedLoading, unchanged_on_failure
from sb3_dipper.common.validation import (
    CheckedPredict,
    InvalidSetting,
    as_int,
    check_compute_reward_for_her,
    check_flat_sac_settings,
    policy_class_and_goal_env,
)
from sb3_dipper.sac_demo.policies import MlpPolicy, MultiInputPolicy

SelfSACDemo = TypeVar("SelfSACDemo", bound="SACDemo")

# A model loaded without an env, only to predict, gets a replay buffer of this size (SB3 builds no HerReplayBuffer
# without an env).
PREDICT_ONLY_BUFFER_SIZE = 1

# SACDemo's demo_kwargs keys: the hierarchies', but normalize_from_demos (scaling the inputs by the demonstrations'
# states), which it does not have.
SAC_DEMO_KWARGS = tuple(key for key in DEFAULT_DEMO_KWARGS if key != "normalize_from_demos")
# The cloning settings DemoSAC's update reads as attributes of its own.
CLONING_SETTINGS = ("demo_share", "bc_coef", "rl_coef", "q_filter")


def _cloning_setting(key: str) -> property:
    """DemoSAC's cloning setting ``key``, read and written in ``demo_kwargs``, where SACDemo keeps it."""

    def setting(model: SACDemo) -> Any:
        return model.demo_kwargs[key]

    def set_setting(model: SACDemo, value: Any) -> None:
        model.demo_kwargs[key] = value

    return property(setting, set_setting, doc=f"``demo_kwargs[{key!r}]``")


class SACDemo(CheckedPredict, CheckedLoading, DemoSAC):
    """SAC+HER whose actor also clones Q-filtered demonstrations, as the hierarchies' lower level does (see the module
    docstring). Without ``demo_kwargs["demo_path"]``, SB3's ``SAC``. The SAC parameters are SB3's, with SB3's defaults;
    the demonstration settings are the hierarchies' ``demo_kwargs``, with their defaults.

    :param policy: ``"MlpPolicy"`` or ``"MultiInputPolicy"`` (both SAC's ``MultiInputPolicy``: goal envs are Dict)
    :param env: a goal env (Dict observations with ``observation``, ``achieved_goal``, ``desired_goal``)
    :param learning_rate: learning rate of the actor, critics and entropy coefficient
    :param buffer_size: replay buffer size
    :param learning_starts: steps of uniformly random actions before learning
    :param batch_size: minibatch size (replay and demonstration transitions together)
    :param tau: target smoothing coefficient
    :param gamma: discount factor
    :param train_freq: train every ``train_freq`` steps (or ``(n, "episode")``)
    :param gradient_steps: gradient steps per training round (-1: as many as env steps collected)
    :param action_noise: extra action noise
    :param replay_buffer_class: replay buffer class (``HerReplayBuffer`` relabels the agent's goals, as the
        demonstrations' are)
    :param replay_buffer_kwargs: its keyword arguments
    :param optimize_memory_usage: SB3's memory-efficient replay buffer variant
    :param n_steps: SB3's n-step returns (1: none); must be 1 with a ``demo_path``, whose update uses one-step targets
    :param ent_coef: entropy coefficient (``"auto"`` learns it)
    :param target_update_interval: target network update interval (gradient steps)
    :param target_entropy: target entropy of the learned entropy coefficient
    :param use_sde: generalized state-dependent exploration (without a ``demo_path`` only: the cloning update does not
        resample its noise)
    :param sde_sample_freq: gSDE noise resampling frequency
    :param use_sde_at_warmup: gSDE instead of uniform actions before learning starts
    :param demo_kwargs: the demonstrations and their cloning, a dict with the hierarchies' keys (see
        :class:`~sb3_dipper.common.hierarchical.HierarchicalAlgorithm`) but ``normalize_from_demos``: ``demo_path``
        (an npz file, a Minari dataset directory, ``"auto"`` for the task's single default scripted demonstration or
        ``"auto:dart<N>"`` for N DART episodes of its scripted expert,
        :func:`~sb3_dipper.common.demonstrations.demonstrations_for`; default ``None``: no cloning, SB3's SAC),
        ``n_demos`` (episodes used, from the first; default: all N of ``"auto:dart<N>"``, the one of ``"auto"``, the
        first episode of a file or dataset), ``demo_share`` (fraction of each batch drawn from the demonstrations,
        0.125), ``bc_coef`` (weight of the behaviour-cloning loss, PIPER's lambda_2, 0.0078), ``rl_coef`` (weight of
        SAC's actor loss while cloning, PIPER's lambda_1, 1e-3) and ``q_filter`` (clone only demo actions the critic
        values above the policy's, ``True``), for example ``dict(demo_path="auto", bc_coef=0.02)``;
        ``model.demo_kwargs`` holds them all (DemoSAC's attributes ``model.bc_coef``, ... read and write it)
    :param stats_window_size: window of the rollout statistics
    :param tensorboard_log: tensorboard folder
    :param policy_kwargs: keyword arguments of SAC's policy
    :param verbose: verbosity
    :param seed: random seed
    :param device: torch device
    :param _init_setup_model: build the networks now
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"MlpPolicy": MlpPolicy, "MultiInputPolicy": MultiInputPolicy}
    # The demonstration settings, checked and completed with their defaults once the model is built.
    demo_kwargs: dict[str, Any]
    demo_share = _cloning_setting("demo_share")
    bc_coef = _cloning_setting("bc_coef")
    rl_coef = _cloning_setting("rl_coef")
    q_filter = _cloning_setting("q_filter")

    def __init__(
        self,
        policy: str | type[MultiInputPolicy],
        env: GymEnv | str | None,
        learning_rate: float | Schedule = 3e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        ent_coef: str | float = "auto",
        target_update_interval: int = 1,
        target_entropy: str | float = "auto",
        use_sde: bool = False,
        sde_sample_freq: int = -1,
        use_sde_at_warmup: bool = False,
        demo_kwargs: dict[str, Any] | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        policy, env = policy_class_and_goal_env(self, policy, env, verbose)
        self.demo_kwargs = dict(demo_kwargs or {})
        super().__init__(
            policy,
            env,
            learning_rate,
            buffer_size,
            learning_starts,
            batch_size,
            tau,
            gamma,
            train_freq,
            gradient_steps,
            action_noise,
            replay_buffer_class=replay_buffer_class,
            # Copies: SB3's SAC adds use_sde to its policy_kwargs, and a caller may pass the same dict to another model.
            replay_buffer_kwargs=dict(replay_buffer_kwargs or {}),
            optimize_memory_usage=optimize_memory_usage,
            n_steps=n_steps,
            ent_coef=ent_coef,
            target_update_interval=target_update_interval,
            target_entropy=target_entropy,
            use_sde=use_sde,
            sde_sample_freq=sde_sample_freq,
            use_sde_at_warmup=use_sde_at_warmup,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            policy_kwargs=dict(policy_kwargs or {}),
            verbose=verbose,
            seed=seed,
            device=device,
            _init_setup_model=False,
            # DemoSAC sets its cloning settings, which live in demo_kwargs: the ones given stay as they are.
            **{key: self.demo_kwargs[key] for key in CLONING_SETTINGS if key in self.demo_kwargs},
        )
        if _init_setup_model:
            self._setup_model()

    @classmethod
    def setting_groups(cls) -> set[str]:
        """:meth:`~sb3_dipper.common.loading.CheckedLoading.setting_groups`, and ``demo_kwargs`` as the hierarchies'."""
        return {*super().setting_groups(), "demo_kwargs"}

    # ---------------------------------------------------------------------------------------------------- set-up

    def _check_settings(self) -> None:
        super()._check_settings()
        # Settings may arrive as floats or strings (zoo -params, YAML 5e4): coerce or refuse them here, not in training.
        check_flat_sac_settings(self)
        self.n_steps = as_int("n_steps", self.n_steps, 1)
        self.demo_kwargs = checked_demo_kwargs(self.demo_kwargs, SAC_DEMO_KWARGS)
        if self.demo_kwargs["demo_path"] is None:
            return
        # The cloning update (DemoSAC.train) bootstraps one step with gamma and draws no gSDE noise.
        if self.n_steps != 1:
            raise InvalidSetting(
                "n_steps",
                f"n_steps={self.n_steps} with a demo_path: the cloning update uses one-step targets; set n_steps=1, or "
                "leave demo_kwargs['demo_path'] out for SB3's SAC with n-step returns",
            )
        if self.use_sde:
            raise InvalidSetting(
                "use_sde",
                "use_sde=True with a demo_path: the cloning update does not resample gSDE noise; set use_sde=False, or "
                "leave demo_kwargs['demo_path'] out for SB3's SAC with gSDE",
            )

    def _setup_model(self) -> None:
        self._check_settings()
        check_compute_reward_for_her(self)
        self._predict_only = self.env is None
        if self._predict_only:
            # A model loaded to predict needs no training data (and SB3 builds a HerReplayBuffer only with an env).
            self.replay_buffer = DictReplayBuffer(
                PREDICT_ONLY_BUFFER_SIZE,
                self.observation_space,  # type: ignore[arg-type]
                self.action_space,
                self.device,
            )
        super()._setup_model()
        cloning = self.demo_kwargs["demo_path"] is not None
        self.demonstrations = self._demonstration_buffer() if cloning and self.env is not None else None

    def _demonstration_buffer(self) -> DemonstrationBuffer:
        """The first ``n_demos`` episodes of ``demo_path`` (``demo_kwargs``), checked against the env's spaces, with their
        actions in the policy's [-1, 1] scale and the env's own goals."""
        demo_path = self.demo_kwargs["demo_path"]
        assert self.env is not None and demo_path is not None and isinstance(self.action_space, spaces.Box)
        demonstrations = demonstrations_for(demo_path, self.env, self.demo_kwargs["n_demos"])
        # Checked here, at construction: a mismatch would otherwise surface at the first update as a tensor-size error.
        demonstrations.check_spaces(self.observation_space, self.action_space)
        actions = np.clip(demonstrations.actions, self.action_space.low, self.action_space.high)
        return DemonstrationBuffer(demonstrations, EnvGoals(self._env_reward), self.policy.scale_action(actions))

    def _env_reward(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, infos: list[dict[str, Any]]) -> np.ndarray:
        """The current env's ``compute_reward``, called as SB3's ``HerReplayBuffer`` calls it (first env)."""
        assert self.env is not None
        return self.env.env_method("compute_reward", achieved_goal, desired_goal, infos, indices=[0])[0]

    # ---------------------------------------------------------------------------------------------------- learning

    def learn(
        self: SelfSACDemo,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "SACDemo",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfSACDemo:
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    def _setup_learn(self, *args: Any, **kwargs: Any) -> Any:
        if self._predict_only:
            raise ValueError(
                "This SACDemo model was loaded without an env, only to predict: give it one with model.set_env(env) "
                "or SACDemo.load(path, env=...)"
            )
        return super()._setup_learn(*args, **kwargs)

    @unchanged_on_failure
    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        """SB3's ``set_env``. A model loaded without an env (a predict-only buffer) is rebuilt for ``env`` around its
        networks and optimizers, with its configured ``buffer_size`` and the demonstrations; load a saved buffer with
        ``load_replay_buffer`` after ``set_env``. The demonstrations' rewards come from the current env."""
        super().set_env(env, force_reset)
        if self._predict_only:
            # SAC builds the configured buffer only where there is none (a HerReplayBuffer needs the env).
            self.replay_buffer = None
            self._rebuild_keeping_parameters()

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """SB3's SAC update, or with a ``demo_path`` DemoSAC's update on replay and demonstration transitions."""
        if isinstance(self.replay_buffer, HerReplayBuffer) and not has_finished_episode(self.replay_buffer):
            # A model resumed with an empty buffer (load or set_env) must first finish an episode: HER samples none before.
            return
        super().train(gradient_steps, batch_size)

    # ---------------------------------------------------------------------------------------------------- saving

    def _excluded_save_params(self) -> list[str]:
        # The demonstrations are read again from demo_kwargs' demo_path when the model is loaded with an env.
        return [*super()._excluded_save_params(), "demonstrations", "_predict_only"]
