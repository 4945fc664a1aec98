"""RAPS: a higher-level policy over parameterised scripted primitives (Dalal, Pathak, Salakhutdinov, "Accelerating
Robotic Reinforcement Learning via Parameterized Action Primitives", NeurIPS 2021, https://arxiv.org/abs/2110.15360;
code https://github.com/mihdalal/raps), as the DIPPER paper's baseline (the authors' PIPER code, ``--raps=1``).

The higher level is HIER's: an SB3 SAC with ``HerReplayBuffer`` trained with the env's sparse reward at the end of
each option. Its action is ``[arguments..., selector]``: the selector picks a primitive of the env's library (see
:mod:`sb3_dipper.raps.primitives`), which runs for ``option_steps`` primitive steps. There is no learned lower level.

Differences from the paper, as in the DIPPER authors' baseline: a small library (reach, open/close gripper) in place of
RAPS's twelve, one selector dimension cut into equal bins in place of one logit per primitive, SAC+HER on states in
place of Dreamer on images. Our bins give each primitive the same share of random exploration (the authors' Fetch
selector gives reach only ``|s| < 0.1``). On the kitchen the primitive is a joint-target controller of our own, which is
neither the paper's description (RAPS's own primitives) nor the authors' code (the first 9 dimensions of the subgoal
used directly as the action): see :mod:`sb3_dipper.raps.primitives`.
"""

from __future__ import annotations

import os
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule

from sb3_dipper.common.demonstrations import Demonstrations
from sb3_dipper.common.files import read_replay_buffer, replay_buffer_path, save_replay_buffer_file
from sb3_dipper.common.hierarchical import has_finished_episode
from sb3_dipper.common.low_level import sac_torch_save_params
from sb3_dipper.common.option_env import DictObs, PrimitiveTransition
from sb3_dipper.common.subgoals import SubgoalSpace, resolve_subgoal_space
from sb3_dipper.hier.hier import HIER
from sb3_dipper.raps.policies import MlpPolicy, MultiInputPolicy
from sb3_dipper.raps.primitives import (
    PrimitiveLibrary,
    PrimitiveSpace,
    dispatch_primitives,
    primitive_library,
    primitive_space,
)

SelfRAPS = TypeVar("SelfRAPS", bound="RAPS")


class ScriptedLowLevel:
    """RAPS's lower level: the chosen primitive of each env, recomputed from every observation. It learns nothing.

    Besides the option layer's controller protocol (``act``, ``value``) it answers what the hierarchical learn loop asks
    of a lower learner (``store``, ``set_logger``, ``replay_buffer``, ``random_actions``) with nothing to do.

    :param library: the primitives
    """

    replay_buffer: ReplayBuffer | None = None

    def __init__(self, library: PrimitiveLibrary) -> None:
        self.library = library
        # Random lower actions before learning_starts do not apply: the higher level's random choices explore.
        self.random_actions = False

    def act(self, low_obs: DictObs, deterministic: bool, normalized: bool = False) -> np.ndarray:
        """Primitive actions; ``desired_goal`` holds each env's ``[arguments, selector]`` (raw observations)."""
        return dispatch_primitives(self.library, low_obs["observation"], low_obs["desired_goal"])

    def value(self, low_obs: DictObs) -> np.ndarray | None:
        return None

    def store(self, transition: PrimitiveTransition) -> None:
        """Nothing to learn from primitive steps."""

    def set_logger(self, logger: Any) -> None:
        """Nothing to log."""


class RAPS(HIER):
    """RAPS as the DIPPER paper's baseline: a SAC+HER higher level chooses scripted primitives and their arguments.

    :param policy: the higher SAC's policy (``"MlpPolicy"`` or ``"MultiInputPolicy"``: SAC's ``MultiInputPolicy``)
    :param env: a goal env with a sparse reward (observations not normalised: the primitives read raw positions)
    :param learning_rate: learning rate of the higher SAC
    :param option_steps: K, the primitive steps each chosen primitive runs
    :param subgoal_space: the env's subgoal space, which bounds ``reach`` targets and projects achieved goals (default:
        the env's declared one); after set-up ``subgoal_space`` is the :class:`PrimitiveSpace` of the RAPS action
    :param primitives: the primitive library (default: the one registered for the env id, else ``reach`` only)
    :param high_buffer_size: higher replay buffer size (options)
    :param high_batch_size: higher minibatch size
    :param high_gamma: higher discount factor (per option)
    :param high_tau: higher target smoothing coefficient
    :param high_ent_coef: higher entropy coefficient
    :param high_gradient_steps: higher gradient steps per option
    :param high_replay_buffer_kwargs: higher ``HerReplayBuffer`` kwargs
    :param random_subgoal_prob: probability of a uniformly random primitive and arguments during training
    :param learning_starts: primitive steps of uniformly random choices before the higher level learns
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
    # The scripted library stands where the shared code expects the lower learner and its controller.
    lower: ScriptedLowLevel  # type: ignore[assignment]
    low_level: ScriptedLowLevel  # type: ignore[assignment]

    def __init__(
        self,
        policy: str | type[BasePolicy],
        env: GymEnv | str | None,
        learning_rate: float | Schedule = 1e-3,
        option_steps: int = 15,
        subgoal_space: SubgoalSpace | None = None,
        primitives: PrimitiveLibrary | None = None,
        high_buffer_size: int = 100_000,
        high_batch_size: int = 256,
        high_gamma: float = 0.95,
        high_tau: float = 0.005,
        high_ent_coef: str | float = "auto",
        high_gradient_steps: int = 1,
        high_replay_buffer_kwargs: dict[str, Any] | None = None,
        random_subgoal_prob: float = 0.0,
        learning_starts: int = 3000,
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
            high_buffer_size=high_buffer_size,
            high_batch_size=high_batch_size,
            high_gamma=high_gamma,
            high_tau=high_tau,
            high_ent_coef=high_ent_coef,
            high_gradient_steps=high_gradient_steps,
            high_replay_buffer_kwargs=high_replay_buffer_kwargs,
            random_subgoal_prob=random_subgoal_prob,
            learning_starts=learning_starts,
            max_episode_steps=max_episode_steps,
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            seed=seed,
            device=device,
            _init_setup_model=False,
        )
        if self._vec_normalize_env is not None and self._vec_normalize_env.norm_obs:
            raise ValueError(
                "RAPS's scripted primitives read raw positions from the observations, so the env must not normalise them: "
                "use VecNormalize(env, norm_obs=False) or no VecNormalize."
            )
        self.primitives = primitives
        if _init_setup_model:
            self._setup_model()

    def _setup_model(self) -> None:
        if self.env is not None and not isinstance(self.subgoal_space, PrimitiveSpace):
            target = resolve_subgoal_space(self.env, self.subgoal_space)
            if self.primitives is None:
                spec = self.env.get_attr("spec", indices=[0])[0]
                self.primitives = primitive_library(getattr(spec, "id", None), target, self.action_space)  # type: ignore[arg-type]
            self.subgoal_space = primitive_space(self.primitives, target)
        super()._setup_model()

    def _env_declared_subgoal_space(self) -> SubgoalSpace:
        """The env's space the primitives' arguments were built for (their ``target``)."""
        assert isinstance(self.subgoal_space, PrimitiveSpace) and self.subgoal_space.target is not None
        return self.subgoal_space.target

    def _setup_low_level(self, demonstrations: Demonstrations | None = None) -> None:
        assert self.primitives is not None, "a saved model always carries its primitives"
        self.low_level = self.lower = ScriptedLowLevel(self.primitives)

    def _acting_low_level(self) -> ScriptedLowLevel:
        """The scripted primitives act as they do in training."""
        return self.low_level

    def learn(
        self: SelfRAPS,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "RAPS",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfRAPS:
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    def _train_low_level(self) -> None:
        """Scripted primitives learn nothing."""

    def _has_training_data(self) -> bool:
        return has_finished_episode(self.higher.replay_buffer)

    # ---------------------------------------------------------------------------------------------------- saving

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "lower"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        return sac_torch_save_params(self.higher, "higher")

    @property
    def replay_buffer(self) -> ReplayBuffer | None:
        """The higher replay buffer, the only one (so that ``CheckpointCallback(save_replay_buffer=True)`` saves it)."""
        return self.higher.replay_buffer

    def save_replay_buffer(self, path: Any) -> None:
        """The higher replay buffer as SB3 pickles it; a file is written under a temporary name and renamed into place."""
        if isinstance(path, (str, os.PathLike)):
            path = replay_buffer_path(path, "RAPS.save_replay_buffer", reading=False)
            save_replay_buffer_file(path, self.higher.replay_buffer)
        else:
            self.higher.save_replay_buffer(path)

    def load_replay_buffer(self, path: Any, truncate_last_traj: bool = True) -> None:
        """Load what :meth:`save_replay_buffer` wrote; it is checked against the model before it replaces anything."""
        if isinstance(path, (str, os.PathLike)):
            path = replay_buffer_path(path, "RAPS.load_replay_buffer", reading=True)
        self.higher.replay_buffer = read_replay_buffer(path, self.higher, truncate_last_traj)
