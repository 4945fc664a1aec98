"""DAC: Discriminator-Actor-Critic, off-policy adversarial imitation from demonstrations, on SB3's SAC.

Paper: Kostrikov, Agrawal, Dwibedi, Levine, Tompson, "Discriminator-Actor-Critic: Addressing Sample Inefficiency and
Reward Bias in Adversarial Imitation Learning", ICLR 2019 (https://arxiv.org/abs/1809.02925). Official code:
``google-research/google-research/dac`` (TensorFlow, TD3); this port keeps its discriminator, losses and absorbing-state
handling and puts them on SB3's SAC, the off-policy learner of every other method in this package.

What makes DAC, and where it is here:

- A discriminator ``D`` tells expert transitions from replay transitions (not from fresh on-policy rollouts: the
  paper's off-policy objective, importance weights dropped as the paper does). Its loss is GAIL's cross-entropy plus
  WGAN-GP's gradient penalty of weight 10 on interpolates between expert and replay inputs (Gulrajani et al. 2017,
  Eq. 3): :func:`discriminator_loss`, :func:`gradient_penalty`.
- The reward is AIRL's ``r(s, a) = log D(s, a) - log(1 - D(s, a))``, which can be positive or negative, unlike GAIL's
  ``-log(1 - D)`` (always positive: a survival bonus) or ``log D`` (always negative: an incentive to end episodes). It is
  recomputed from the current discriminator for every sampled batch and never stored (:func:`adversarial_reward`).
- Absorbing states: an episode that ends by termination (not by the time limit) continues into an absorbing state
  ``s_a`` (observation zeroed, an indicator dimension set to 1) that loops on itself under the zero action, so its
  reward is learned like any other: ``R_T = r(s_T, a_T) + sum_{t > T} gamma^{t - T} r(s_a, .)``. The target bootstraps
  through ``s_a``, the next action there is 0 and the actor is not trained on it (:func:`to_absorbing`,
  :func:`absorb_terminations`, :func:`expert_transitions`). Time-limit ends bootstrap as usual.

Adaptations to goal-conditioned tasks (documented in the class):

- ``D(s, a, g)`` sees the desired goal (``goal_conditioned_discriminator``), and expert goals are relabelled with goals
  the demonstration achieved later as HER relabels the replay side (goal-conditioned GAIL of Ding et al. 2019): by
  default with the ``HerReplayBuffer``'s own probability, and not at all without HER, so that both sides are relabelled
  alike; otherwise ``D`` could tell expert from policy by the goals alone (one demonstration has one goal;
  relabelled expert rows, whose goal the episode reaches, against unrelabelled replay rows, whose goal is rarely reached).
- The absorbing indicator is a fourth observation key, ``"absorbing"``, so ``VecNormalize`` leaves it alone; the absorbing
  state keeps its achieved and desired goals, which HER needs to relabel the final transition. The tasks of this package
  never terminate (episodes end at the time limit), so there ``absorbing_states=True`` changes nothing: the indicator
  is always 0 (a constant-zero input leaves every network output unchanged) and no absorbing transition is ever made.
- Demonstration files record episode lengths, not how episodes ended: an expert episode counts as ended by
  termination only if it is shorter than both the time limit registered for its env id and the training env's.
- The self-transitions ``(s_a, 0, s_a)`` live beside the replay buffer (SB3's buffers write one row for every env at
  once) and are mixed into each batch in proportion to their number, as if they were in it.

Not reproduced: TD3 (SAC instead), subsampling of expert trajectories every 20 steps and the matching reweighting of
absorbing expert samples (we use whole demonstrations, so there is nothing to reweight).

``paper_compat=True`` is the DIPPER authors' "DAC" (``Utsavz/piper``, ``ddpg.py``): a least-squares discriminator with
targets +1 (expert) and -1 (policy), ReLU layers, the raw output ``D(s, a, g)`` as reward, no gradient penalty and no
absorbing states. (Their code scores the current policy's action at replay states rather than the stored action, and
clips SAC targets to ``[-1 / (1 - gamma), 0]``; neither is reproduced.)
"""

from __future__ import annotations

import os
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, TypeVar

import gymnasium as gym
import numpy as np
import torch as th
import torch.nn.functional as F
from gymnasium import spaces
from stable_baselines3 import SAC, HerReplayBuffer
from stable_baselines3.common.buffers import DictReplayBuffer, ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import DictReplayBufferSamples, GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import obs_as_tensor, polyak_update
from torch import nn

from sb3_dipper.common.demonstrations import Demonstrations, demonstrations_for
from sb3_dipper.common.files import (
    read_npz,
    read_replay_buffer,
    replay_buffer_path,
    save_npz,
    save_replay_buffer_file,
)
from sb3_dipper.common.hierarchical import has_finished_episode, sibling_path
from sb3_dipper.common.loading import CheckedLoading, unchanged_on_failure
from sb3_dipper.common.validation import (
    InvalidSetting,
    as_bool,
    as_demo_path,
    as_float,
    as_optional_float,
    as_optional_int,
    check_compute_reward_for_her,
    check_flat_sac_settings,
    checked_goal_observation,
    policy_class_and_goal_env,
)
from sb3_dipper.dac.policies import Discriminator, MlpPolicy, MultiInputPolicy

SelfDAC = TypeVar("SelfDAC", bound="DAC")

DictObs = dict[str, np.ndarray]

# The absorbing indicator: an observation key of its own, so VecNormalize never normalises it.
ABSORBING_KEY = "absorbing"
# A model loaded without an env, only to predict, gets buffers of this size (SB3 builds no HerReplayBuffer without one).
PREDICT_ONLY_BUFFER_SIZE = 1


# ---------------------------------------------------------------------------------------------------- pure functions


def adversarial_reward(logits: th.Tensor) -> th.Tensor:
    """``log D - log(1 - D)`` with ``D = sigmoid(logits)`` (AIRL's reward, used by DAC); it equals the logit."""
    return F.logsigmoid(logits) - F.logsigmoid(-logits)


def discriminator_loss(expert_logits: th.Tensor, policy_logits: th.Tensor) -> th.Tensor:
    """GAIL's discriminator loss: cross-entropy with expert labelled 1 and policy 0, the two means summed (TF-GAN's)."""
    expert_loss = F.binary_cross_entropy_with_logits(expert_logits, th.ones_like(expert_logits))
    policy_loss = F.binary_cross_entropy_with_logits(policy_logits, th.zeros_like(policy_logits))
    return expert_loss + policy_loss


def least_squares_discriminator_loss(expert_outputs: th.Tensor, policy_outputs: th.Tensor) -> th.Tensor:
    """The DIPPER authors' loss: ``mean((2 y - 1 - D)^2)`` over the joined batch, ``y = 1`` for expert, 0 for policy."""
    outputs = th.cat((expert_outputs, policy_outputs))
    targets = th.cat((th.ones_like(expert_outputs), -th.ones_like(policy_outputs)))
    return (targets - outputs).pow(2).mean()


def gradient_penalty(
    discriminator: Callable[[th.Tensor], th.Tensor], expert_inputs: th.Tensor, policy_inputs: th.Tensor, mix: th.Tensor
) -> th.Tensor:
    """WGAN-GP's penalty ``E[(||grad_x D(x_hat)||_2 - 1)^2]`` (Gulrajani et al. 2017, Eq. 3), as DAC applies it.

    ``x_hat = mix * policy_inputs + (1 - mix) * expert_inputs`` row by row (``mix`` of shape ``(N, 1)``, uniform in
    ``[0, 1]`` in training). The graph is kept, so the penalty trains the discriminator.
    """
    interpolates = (mix * policy_inputs + (1.0 - mix) * expert_inputs).detach().requires_grad_(True)
    (gradients,) = th.autograd.grad(discriminator(interpolates).sum(), interpolates, create_graph=True)
    return (gradients.norm(dim=-1) - 1.0).pow(2).mean()


def with_absorbing_indicator(observations: DictObs, value: float) -> DictObs:
    """The observations with the absorbing indicator (shape ``(..., 1)``) set to ``value``."""
    indicator = np.full((*observations["observation"].shape[:-1], 1), value, dtype=np.float32)
    return {**observations, ABSORBING_KEY: indicator}


def to_absorbing(observations: DictObs) -> DictObs:
    """The absorbing state after each row: observation zeroed, indicator 1, achieved and desired goals kept.

    The goals stay so that HER can still relabel the transition into the absorbing state with the goal it achieved.
    """
    absorbing = with_absorbing_indicator(observations, 1.0)
    absorbing["observation"] = np.zeros_like(observations["observation"])
    return absorbing


def absorb_terminations(
    next_observations: DictObs, dones: np.ndarray, infos: list[dict[str, Any]]
) -> tuple[DictObs, list[dict[str, Any]], np.ndarray]:
    """Send every episode that ended by termination (done, not truncated) into the absorbing state.

    Returns the next observations (indicator set; the absorbing state where an episode terminated), the infos (a
    terminated episode is marked ``TimeLimit.truncated``, so SB3's buffer stores it as not done and the target bootstraps
    through the absorbing state, as DAC's does) and the boolean mask of terminated envs.
    """
    truncated = np.array([info.get("TimeLimit.truncated", False) for info in infos], dtype=bool)
    terminated = np.asarray(dones, dtype=bool) & ~truncated
    next_observations = with_absorbing_indicator(next_observations, 0.0)
    if not terminated.any():
        return next_observations, infos, terminated
    absorbing = to_absorbing({key: value[terminated] for key, value in next_observations.items()})
    next_observations = {key: value.copy() for key, value in next_observations.items()}
    for key, value in absorbing.items():
        next_observations[key][terminated] = value
    infos = [{**info, "TimeLimit.truncated": True} if ended else info for info, ended in zip(infos, terminated, strict=True)]
    return next_observations, infos, terminated


@dataclass
class ExpertTransitions:
    """The discriminator's expert side: ``(s, a)`` rows of the demonstrations, goals relabelled at sampling.

    ``episode_ends[i]`` is one past the last row of row ``i``'s episode; ``next_achieved_goals`` gives the goals a row's
    episode achieved from that row on (HER's "future" goals).
    """

    observations: DictObs
    actions: np.ndarray
    next_achieved_goals: np.ndarray
    episode_ends: np.ndarray

    def __len__(self) -> int:
        return int(self.actions.shape[0])

    def sample(self, batch_size: int, relabel_prob: float, rng: np.random.Generator) -> tuple[DictObs, np.ndarray]:
        """``(observations, actions)`` of ``batch_size`` rows; with ``relabel_prob`` a row's goal becomes a future one."""
        rows = rng.integers(len(self), size=batch_size)
        observations = {key: value[rows] for key, value in self.observations.items()}
        future = rows + (rng.random(batch_size) * (self.episode_ends[rows] - rows)).astype(np.int64)
        relabel = rng.random(batch_size) < relabel_prob
        observations["desired_goal"] = np.where(
            relabel[:, None], self.next_achieved_goals[future], observations["desired_goal"]
        ).astype(np.float32)
        return observations, self.actions[rows]


def expert_transitions(
    demonstrations: Demonstrations, scaled_actions: np.ndarray, time_limit: int | None, absorbing_states: bool
) -> ExpertTransitions:
    """The expert rows of the demonstrations; with ``absorbing_states``, the indicator and absorbing rows.

    An episode shorter than ``time_limit`` ended by termination: with ``absorbing_states`` it gets one more row, the
    absorbing state under the zero action (its transition into the absorbing state only changes the next observation,
    which the discriminator does not see). ``scaled_actions`` are the demonstrated actions in the policy's [-1, 1] space.
    """
    observations: list[DictObs] = []
    actions: list[np.ndarray] = []
    next_achieved: list[np.ndarray] = []
    episode_ends: list[np.ndarray] = []
    n_rows = 0
    for start, length in zip(demonstrations.episode_starts, demonstrations.episode_lengths, strict=True):
        steps = slice(int(start), int(start + length))
        episode_obs = {key: value[steps].astype(np.float32) for key, value in demonstrations.observations.items()}
        episode_actions = scaled_actions[steps].astype(np.float32)
        episode_next_achieved = demonstrations.next_observations["achieved_goal"][steps].astype(np.float32)
        if absorbing_states:
            episode_obs = with_absorbing_indicator(episode_obs, 0.0)
            if time_limit is not None and length < time_limit:
                last = {key: value[steps][-1:] for key, value in demonstrations.next_observations.items()}
                absorbing = to_absorbing({key: value.astype(np.float32) for key, value in last.items()})
                episode_obs = {key: np.concatenate((value, absorbing[key])) for key, value in episode_obs.items()}
                episode_actions = np.concatenate((episode_actions, np.zeros_like(episode_actions[:1])))
                episode_next_achieved = np.concatenate((episode_next_achieved, episode_next_achieved[-1:]))
        observations.append(episode_obs)
        actions.append(episode_actions)
        next_achieved.append(episode_next_achieved)
        n_rows += len(episode_actions)
        episode_ends.append(np.full(len(episode_actions), n_rows, dtype=np.int64))
    return ExpertTransitions(
        observations={key: np.concatenate([episode[key] for episode in observations]) for key in observations[0]},
        actions=np.concatenate(actions),
        next_achieved_goals=np.concatenate(next_achieved),
        episode_ends=np.concatenate(episode_ends),
    )


# ---------------------------------------------------------------------------------------------------- absorbing data


class AbsorbingTransitions:
    """The self-transitions ``(s_a, 0, s_a)``, one per episode that ended by termination, kept beside the replay buffer.

    :param observation_space: the networks' observation space (with the absorbing indicator)
    :param capacity: most self-transitions kept (oldest overwritten first)
    """

    def __init__(self, observation_space: spaces.Dict, capacity: int) -> None:
        self.capacity = capacity
        self.observations = {
            key: np.zeros((capacity, *(space.shape or ())), dtype=np.float32)
            for key, space in observation_space.spaces.items()
        }
        self.pos = 0
        self.full = False

    def __len__(self) -> int:
        return self.capacity if self.full else self.pos

    def add(self, absorbing: DictObs) -> None:
        """Add the absorbing states (rows of a batch) of episodes that just terminated."""
        for row in range(len(absorbing["observation"])):
            for key, store in self.observations.items():
                store[self.pos] = absorbing[key][row]
            self.pos = (self.pos + 1) % self.capacity
            self.full = self.full or self.pos == 0

    def sample(self, batch_size: int, rng: np.random.Generator) -> DictObs:
        rows = rng.integers(len(self), size=batch_size)
        return {key: value[rows] for key, value in self.observations.items()}

    def state_dict(self) -> dict[str, np.ndarray]:
        return {**self.observations, "position": np.array([self.pos, int(self.full)])}

    def load_state_dict(self, arrays: dict[str, np.ndarray]) -> None:
        for key in self.observations:
            self.observations[key][...] = arrays[key]
        self.pos, full = (int(value) for value in arrays["position"])
        self.full = bool(full)


class _AbsorbingStateWriter:
    """What SB3's ``_store_transition`` writes to: it adds the indicator, swaps the observation after a termination for
    the absorbing state, then hands the transition to the replay buffer and the self-transition to its own store.

    SB3 has already found the real next observations (the terminal ones at episode ends, unnormalised).
    """

    def __init__(self, replay_buffer: ReplayBuffer, absorbing_transitions: AbsorbingTransitions) -> None:
        self.replay_buffer = replay_buffer
        self.absorbing_transitions = absorbing_transitions

    def add(
        self,
        obs: DictObs,
        next_obs: DictObs,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        next_obs, infos, terminated = absorb_terminations(next_obs, done, infos)
        self.replay_buffer.add(with_absorbing_indicator(obs, 0.0), next_obs, action, reward, done, infos)  # type: ignore[arg-type]
        if terminated.any():
            self.absorbing_transitions.add({key: value[terminated] for key, value in next_obs.items()})


# ---------------------------------------------------------------------------------------------------- the algorithm


class DAC(CheckedLoading, SAC):
    """DAC (Kostrikov et al., ICLR 2019): SAC on rewards from a discriminator of expert versus replay transitions.

    Each gradient step: one discriminator update on a replay batch and an expert batch (cross-entropy plus gradient
    penalty), then SAC's updates on that replay batch with rewards ``log D - log(1 - D)`` recomputed by the updated
    discriminator. The environment's reward is never used. The SAC parameters are SB3's; see the module docstring for
    the absorbing states and the goal-conditioned adaptations.

    :param policy: ``"MlpPolicy"`` or ``"MultiInputPolicy"`` (both SAC's ``MultiInputPolicy``: goal envs are Dict)
    :param env: a goal env (Dict observations with ``observation``, ``achieved_goal``, ``desired_goal``)
    :param learning_rate: learning rate of the actor, critics and entropy coefficient
    :param buffer_size: replay buffer size
    :param learning_starts: steps of uniformly random actions before learning (DAC: 1k to 10k)
    :param batch_size: minibatch size of the replay batch and of the expert batch
    :param tau: target smoothing coefficient
    :param gamma: discount factor
    :param train_freq: train every ``train_freq`` steps (or ``(n, "episode")``)
    :param gradient_steps: gradient steps (each with one discriminator update) per training round
    :param action_noise: extra action noise
    :param replay_buffer_class: replay buffer class (``HerReplayBuffer`` relabels the policy's goals)
    :param replay_buffer_kwargs: its keyword arguments
    :param optimize_memory_usage: SB3's memory-efficient replay buffer variant
    :param ent_coef: entropy coefficient (``"auto"`` learns it)
    :param target_update_interval: target network update interval (gradient steps)
    :param target_entropy: target entropy of the learned entropy coefficient
    :param use_sde: generalized state-dependent exploration
    :param sde_sample_freq: gSDE noise resampling frequency
    :param use_sde_at_warmup: gSDE instead of uniform actions before learning starts
    :param demo_path: the expert data: ``"auto"`` (the task's single default scripted demonstration), ``"auto:dart<N>"``
        (N DART episodes of its scripted expert), an npz file or a Minari dataset directory (see
        :mod:`sb3_dipper.common.demonstrations`), as a str or a ``pathlib.Path``
    :param n_demos: how many demonstration episodes to use, from the first (the DIPPER paper: one; default: all N of
        ``"auto:dart<N>"``, the one of ``"auto"``, the first episode of a file or dataset)
    :param goal_conditioned_discriminator: feed the desired goal to the discriminator, ``D(s, a, g)``
    :param absorbing_states: DAC's absorbing states for episodes that end by termination (no effect on tasks that only
        end at the time limit)
    :param gradient_penalty_coef: weight of the gradient penalty (DAC: 10)
    :param expert_goal_relabel_prob: probability that an expert row's goal is replaced by one its episode achieved
        later (0: the demonstration's own goal); ``None`` matches the replay buffer: a ``HerReplayBuffer``'s relabel
        probability (``her_ratio``), 0 for any other buffer
    :param discriminator_learning_rate: learning rate of the discriminator's Adam
    :param discriminator_net_arch: hidden layers of the discriminator (default: DAC's ``[256, 256]``)
    :param paper_compat: the DIPPER authors' variant (least-squares discriminator, raw output as reward, ReLU layers, no
        gradient penalty, no absorbing states, whatever ``absorbing_states`` and ``gradient_penalty_coef`` say)
    :param stats_window_size: window of the rollout statistics
    :param tensorboard_log: tensorboard folder
    :param policy_kwargs: keyword arguments of SAC's policy
    :param verbose: verbosity
    :param seed: random seed
    :param device: torch device
    :param _init_setup_model: build the networks now
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"MlpPolicy": MlpPolicy, "MultiInputPolicy": MultiInputPolicy}
    discriminator: Discriminator

    def __init__(
        self,
        policy: str | type[MultiInputPolicy],
        env: GymEnv | str | None,
        learning_rate: float | Schedule = 3e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 1000,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        ent_coef: str | float = "auto",
        target_update_interval: int = 1,
        target_entropy: str | float = "auto",
        use_sde: bool = False,
        sde_sample_freq: int = -1,
        use_sde_at_warmup: bool = False,
        demo_path: str | os.PathLike[str] | None = "auto",
        n_demos: int | None = None,
        goal_conditioned_discriminator: bool = True,
        absorbing_states: bool = True,
        gradient_penalty_coef: float = 10.0,
        expert_goal_relabel_prob: float | None = None,
        discriminator_learning_rate: float = 1e-3,
        discriminator_net_arch: list[int] | None = None,
        paper_compat: bool = False,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        policy, env = policy_class_and_goal_env(self, policy, env, verbose)
        super().__init__(
            policy,  # type: ignore[arg-type]
            env,  # type: ignore[arg-type]
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
        )
        self.demo_path: str | None = demo_path  # type: ignore[assignment]  # a path-like becomes its str in _check_settings
        self.n_demos = n_demos
        self.goal_conditioned_discriminator = goal_conditioned_discriminator
        self.paper_compat = paper_compat
        self.absorbing_states = absorbing_states
        self.gradient_penalty_coef = gradient_penalty_coef
        self.expert_goal_relabel_prob = expert_goal_relabel_prob
        self.discriminator_learning_rate = discriminator_learning_rate
        self.discriminator_net_arch = [256, 256] if discriminator_net_arch is None else discriminator_net_arch
        self._rng = np.random.default_rng(seed)
        if _init_setup_model:
            self._setup_model()

    # ---------------------------------------------------------------------------------------------------- set-up

    def _check_settings(self) -> None:
        super()._check_settings()
        self.demo_path = as_demo_path("demo_path", self.demo_path)
        if self.demo_path is None:
            raise InvalidSetting(
                "demo_path", 'DAC imitates demonstrations: pass demo_path="auto", an npz file or a Minari dataset directory'
            )
        # Settings may arrive as floats or strings (zoo -params, YAML 5e4): coerce or refuse them here, not in training.
        self.n_demos = as_optional_int("n_demos", self.n_demos, 1, "DAC needs at least one demonstration episode")
        check_flat_sac_settings(self)
        self.goal_conditioned_discriminator = as_bool("goal_conditioned_discriminator", self.goal_conditioned_discriminator)
        self.paper_compat = as_bool("paper_compat", self.paper_compat)
        self.discriminator_learning_rate = as_float(
            "discriminator_learning_rate", self.discriminator_learning_rate, 0.0, low_open=True
        )
        # The authors' variant has no absorbing states, whatever absorbing_states says.
        self.absorbing_states = as_bool("absorbing_states", self.absorbing_states) and not self.paper_compat
        self.gradient_penalty_coef = as_float(
            "gradient_penalty_coef", self.gradient_penalty_coef, 0.0, reason="it weighs a loss"
        )
        self.expert_goal_relabel_prob = as_optional_float("expert_goal_relabel_prob", self.expert_goal_relabel_prob, 0.0, 1.0)

    def _setup_model(self) -> None:
        self._check_settings()
        check_compute_reward_for_her(self)
        env_observation_space = self.observation_space
        network_space = self._network_observation_space()
        self._predict_only = self.env is None
        if self._predict_only:
            # A model loaded to predict needs no training data (and SB3 builds a HerReplayBuffer only with an env).
            self.replay_buffer = DictReplayBuffer(PREDICT_ONLY_BUFFER_SIZE, network_space, self.action_space, self.device)
        # The replay buffer and the networks see the absorbing indicator; the env and the saved spaces do not (predict()
        # adds the indicator), so the model loads and runs on the plain env.
        self.observation_space = network_space
        super()._setup_model()
        self.observation_space = env_observation_space
        self.discriminator = Discriminator(
            self._discriminator_input_dim(network_space),
            self.discriminator_net_arch,
            nn.ReLU if self.paper_compat else nn.Tanh,
            self.discriminator_learning_rate,
            orthogonal_init=not self.paper_compat,
        ).to(self.device)
        self.absorbing_transitions = (
            AbsorbingTransitions(network_space, PREDICT_ONLY_BUFFER_SIZE if self._predict_only else self.buffer_size)
            if self.absorbing_states
            else None
        )
        self.expert: ExpertTransitions | None = self._load_expert() if self.env is not None else None

    def _network_observation_space(self) -> spaces.Dict:
        """The env's observation space, plus the absorbing indicator when absorbing states are on."""
        assert isinstance(self.observation_space, spaces.Dict)
        if not self.absorbing_states:
            return self.observation_space
        return spaces.Dict({**self.observation_space.spaces, ABSORBING_KEY: spaces.Box(0.0, 1.0, (1,), np.float32)})

    def _discriminator_keys(self, observation_space: spaces.Dict) -> list[str]:
        """The observation keys the discriminator sees: the state (with the absorbing indicator) and, last, the goal."""
        keys = [key for key in observation_space.spaces if key != "desired_goal"]
        return [*keys, "desired_goal"] if self.goal_conditioned_discriminator else keys

    def _discriminator_input_dim(self, observation_space: spaces.Dict) -> int:
        sizes = [int(np.prod(observation_space[key].shape)) for key in self._discriminator_keys(observation_space)]  # type: ignore[arg-type]
        return int(np.prod(self.action_space.shape)) + sum(sizes)  # type: ignore[arg-type]

    def _load_expert(self) -> ExpertTransitions:
        assert self.env is not None and isinstance(self.action_space, spaces.Box) and self.demo_path is not None
        demonstrations = demonstrations_for(self.demo_path, self.env, self.n_demos)
        demonstrations.check_spaces(self.observation_space, self.action_space)
        actions = np.clip(demonstrations.actions, self.action_space.low, self.action_space.high)
        scaled_actions = self.policy.scale_action(actions)
        time_limit = self._demonstration_time_limit(demonstrations)
        return expert_transitions(demonstrations, scaled_actions, time_limit, self.absorbing_states)

    def _demonstration_time_limit(self, demonstrations: Demonstrations) -> int | None:
        """The time limit below which a demonstration episode counts as ended by termination.

        The files do not say how an episode ended, only its length. Both the limit registered for the demonstrations'
        env id and the training env's limit are plausible recording limits; the smaller one is used, because taking a
        time-limit end for a termination would give the expert an absorbing state the policy can never reach, the very
        reward bias absorbing states exist to remove.
        """
        assert self.env is not None
        spec = self.env.get_attr("spec", indices=[0])[0]
        limits = [getattr(spec, "max_episode_steps", None)]
        if demonstrations.env_id in gym.registry:
            limits.append(gym.spec(demonstrations.env_id).max_episode_steps)
        known = [int(limit) for limit in limits if limit is not None]
        return min(known) if known else None

    def learn(
        self: SelfDAC,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "DAC",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfDAC:
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    def _setup_learn(self, *args: Any, **kwargs: Any) -> Any:
        if self._predict_only:
            raise ValueError(
                "This DAC model was loaded without an env, only to predict: give it one with model.set_env(env) "
                "or DAC.load(path, env=...)"
            )
        result = super()._setup_learn(*args, **kwargs)
        if self.expert is None:
            self.expert = self._load_expert()
        return result

    @unchanged_on_failure
    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        """SB3's ``set_env``. A model loaded without an env (predict-only buffers) is rebuilt for ``env`` around its
        networks and optimizers, with its configured ``buffer_size`` and the demonstrations; load saved buffers with
        ``load_replay_buffer`` after ``set_env``."""
        super().set_env(env, force_reset)
        if self._predict_only:
            # SAC builds the configured buffer only where there is none (a HerReplayBuffer needs the env).
            self.replay_buffer = None
            self._rebuild_keeping_parameters()

    # ---------------------------------------------------------------------------------------------------- acting

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """SAC's action; the env's observations never come from an absorbing state, so their indicator is 0. The
        observation is checked first (:func:`~sb3_dipper.common.validation.checked_goal_observation`)."""
        env_keys = observation
        if isinstance(observation, dict):
            env_keys = {key: value for key, value in observation.items() if key != ABSORBING_KEY}
        checked_goal_observation(env_keys, self.observation_space)  # type: ignore[arg-type]
        if self.absorbing_states and isinstance(observation, dict) and ABSORBING_KEY not in observation:
            observation = with_absorbing_indicator({key: np.asarray(value) for key, value in observation.items()}, 0.0)
        return super().predict(observation, state, episode_start, deterministic)

    def _store_transition(
        self,
        replay_buffer: ReplayBuffer,
        buffer_action: np.ndarray,
        new_obs: np.ndarray | dict[str, np.ndarray],
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """SB3's storing, with the absorbing-state treatment of terminated episodes in between."""
        if self.absorbing_transitions is not None:
            replay_buffer = _AbsorbingStateWriter(replay_buffer, self.absorbing_transitions)  # type: ignore[assignment]
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)

    # ---------------------------------------------------------------------------------------------------- training

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """Per gradient step: the discriminator, then SAC on the rewards the updated discriminator gives the batch."""
        if isinstance(self.replay_buffer, HerReplayBuffer) and not has_finished_episode(self.replay_buffer):
            # A model resumed with empty buffers (load or set_env) must first finish an episode: HER samples none before.
            return
        self.policy.set_training_mode(True)
        optimizers = [self.actor.optimizer, self.critic.optimizer]
        if self.ent_coef_optimizer is not None:
            optimizers.append(self.ent_coef_optimizer)
        self._update_learning_rate(optimizers)
        logs: dict[str, list[float]] = defaultdict(list)
        for gradient_step in range(gradient_steps):
            batch = self._policy_batch(batch_size)
            # As SAC does: log_std may have changed since the last step, so the gSDE noise is resampled.
            if self.use_sde:
                self.actor.reset_noise()

            # Discriminator: expert transitions against replay transitions (+ gradient penalty).
            self._update_discriminator(batch, logs)

            # Rewards from the current discriminator, recomputed for this batch and never stored.
            with th.no_grad():
                rewards = self._rewards(batch.observations, batch.actions)
            logs["disc_reward"].append(rewards.mean().item())

            # SAC on those rewards. Absorbing states take the zero action (no entropy there) and train no actor.
            active = ~self._is_absorbing(batch.observations)
            next_absorbing = self._is_absorbing(batch.next_observations)
            actions_pi, log_prob = self.actor.action_log_prob(batch.observations)
            log_prob = log_prob.reshape(-1, 1)
            ent_coef = self._entropy_coefficient(log_prob[active], logs)

            with th.no_grad():
                next_actions, next_log_prob = self.actor.action_log_prob(batch.next_observations)
                next_actions = next_actions.masked_fill(next_absorbing, 0.0)
                next_log_prob = next_log_prob.reshape(-1, 1).masked_fill(next_absorbing, 0.0)
                next_q = th.cat(self.critic_target(batch.next_observations, next_actions), dim=1).min(dim=1, keepdim=True)[0]
                target_q = rewards + (1 - batch.dones) * self.gamma * (next_q - ent_coef * next_log_prob)
            current_q = self.critic(batch.observations, batch.actions)
            critic_loss = 0.5 * sum(F.mse_loss(q, target_q) for q in current_q)
            self.critic.optimizer.zero_grad()
            critic_loss.backward()  # type: ignore[union-attr]
            self.critic.optimizer.step()
            logs["critic_loss"].append(critic_loss.item())  # type: ignore[union-attr]

            min_q_pi = th.cat(self.critic(batch.observations, actions_pi), dim=1).min(dim=1, keepdim=True).values
            actor_loss = (ent_coef * log_prob - min_q_pi)[active].mean()
            self.actor.optimizer.zero_grad()
            actor_loss.backward()
            self.actor.optimizer.step()
            logs["actor_loss"].append(actor_loss.item())

            if gradient_step % self.target_update_interval == 0:
                polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
                polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for key, values in logs.items():
            self.logger.record(f"train/{key}", float(np.mean(values)))

    def _policy_batch(self, batch_size: int) -> DictReplayBufferSamples:
        """A replay batch (normalised as SB3 does), with absorbing self-transitions in proportion to their number."""
        assert self.replay_buffer is not None
        n_absorbing = 0
        if self.absorbing_transitions is not None and len(self.absorbing_transitions) > 0:
            n_stored = self.replay_buffer.size() * self.n_envs
            share = len(self.absorbing_transitions) / (len(self.absorbing_transitions) + n_stored)
            n_absorbing = min(int(self._rng.binomial(batch_size, share)), batch_size - 1)
        replay: DictReplayBufferSamples = self.replay_buffer.sample(batch_size - n_absorbing, env=self._vec_normalize_env)  # type: ignore[arg-type,assignment]
        if n_absorbing == 0:
            return replay
        assert self.absorbing_transitions is not None
        loops = self._tensor_obs(self.absorbing_transitions.sample(n_absorbing, self._rng))
        zeros = th.zeros((n_absorbing, 1), device=self.device)
        return DictReplayBufferSamples(
            observations={key: th.cat((value, loops[key])) for key, value in replay.observations.items()},
            actions=th.cat((replay.actions, th.zeros((n_absorbing, replay.actions.shape[1]), device=self.device))),
            next_observations={key: th.cat((value, loops[key])) for key, value in replay.next_observations.items()},
            dones=th.cat((replay.dones, zeros)),
            rewards=th.cat((replay.rewards, zeros)),
        )

    def _tensor_obs(self, observations: DictObs) -> dict[str, th.Tensor]:
        """Tensors of (VecNormalize-normalised) observations."""
        if self._vec_normalize_env is not None:
            observations = self._vec_normalize_env.normalize_obs(observations)  # type: ignore[assignment]
        return obs_as_tensor(observations, self.device)  # type: ignore[return-value]

    def _discriminator_inputs(self, observations: dict[str, th.Tensor], actions: th.Tensor) -> th.Tensor:
        """``(a, s[, g])`` as one flat vector per row."""
        keys = self._discriminator_keys(self.policy.observation_space)  # type: ignore[arg-type]
        # Buffers keep the env's dtype (often float64); the discriminator, like SB3's policies, works in float32.
        return th.cat([actions, *(observations[key].flatten(start_dim=1) for key in keys)], dim=1).float()

    def _rewards(self, observations: dict[str, th.Tensor], actions: th.Tensor) -> th.Tensor:
        """``log D - log(1 - D)`` of the current discriminator; with ``paper_compat``, its raw output."""
        outputs = self.discriminator(self._discriminator_inputs(observations, actions))
        return outputs if self.paper_compat else adversarial_reward(outputs)

    @property
    def effective_expert_goal_relabel_prob(self) -> float:
        """``expert_goal_relabel_prob`` if set, else the replay buffer's: HER's relabel probability, 0 without HER."""
        if self.expert_goal_relabel_prob is not None:
            return self.expert_goal_relabel_prob
        return self.replay_buffer.her_ratio if isinstance(self.replay_buffer, HerReplayBuffer) else 0.0

    def _update_discriminator(self, batch: DictReplayBufferSamples, logs: dict[str, list[float]]) -> None:
        """One discriminator step on the batch's ``(s, a, g)`` against as many expert rows (goals relabelled)."""
        assert self.expert is not None
        expert_obs, expert_actions = self.expert.sample(len(batch.actions), self.effective_expert_goal_relabel_prob, self._rng)
        expert_actions_tensor = th.as_tensor(expert_actions, device=self.device)
        expert_inputs = self._discriminator_inputs(self._tensor_obs(expert_obs), expert_actions_tensor)
        policy_inputs = self._discriminator_inputs(batch.observations, batch.actions)  # type: ignore[arg-type]
        expert_outputs, policy_outputs = self.discriminator(expert_inputs), self.discriminator(policy_inputs)
        if self.paper_compat:
            loss = least_squares_discriminator_loss(expert_outputs, policy_outputs)
        else:
            loss = discriminator_loss(expert_outputs, policy_outputs)
            mix = th.rand((len(policy_inputs), 1), device=self.device)
            penalty = gradient_penalty(self.discriminator, expert_inputs, policy_inputs, mix)
            logs["gradient_penalty"].append(penalty.item())
            loss = loss + self.gradient_penalty_coef * penalty
        self.discriminator.optimizer.zero_grad()
        loss.backward()
        self.discriminator.optimizer.step()
        logs["disc_loss"].append(loss.item())
        # Both losses put the decision boundary at an output of 0 (D = 1/2 for the cross-entropy).
        logs["disc_expert_accuracy"].append((expert_outputs > 0).float().mean().item())
        logs["disc_policy_accuracy"].append((policy_outputs < 0).float().mean().item())

    def _is_absorbing(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        """``(N, 1)`` booleans: which rows are absorbing states."""
        if ABSORBING_KEY not in observations:
            return th.zeros((len(observations["observation"]), 1), dtype=th.bool, device=self.device)
        return observations[ABSORBING_KEY] > 0.5

    def _entropy_coefficient(self, log_prob: th.Tensor, logs: dict[str, list[float]]) -> th.Tensor:
        """SAC's entropy coefficient; when it is learned, its value before the step its own loss then takes (as SAC)."""
        if self.ent_coef_optimizer is None or self.log_ent_coef is None:
            ent_coef = self.ent_coef_tensor
        else:
            ent_coef = th.exp(self.log_ent_coef.detach())
            assert isinstance(self.target_entropy, float)
            ent_coef_loss = -(self.log_ent_coef * (log_prob + self.target_entropy).detach()).mean()
            self.ent_coef_optimizer.zero_grad()
            ent_coef_loss.backward()
            self.ent_coef_optimizer.step()
            logs["ent_coef_loss"].append(ent_coef_loss.item())
        logs["ent_coef"].append(ent_coef.item())
        return ent_coef

    # ---------------------------------------------------------------------------------------------------- saving

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "expert", "absorbing_transitions", "_predict_only"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        return [*state_dicts, "discriminator", "discriminator.optimizer"], variables

    def save_replay_buffer(self, path: Any) -> None:
        """SB3's replay buffer (pickle at ``path``) and, beside it, the absorbing self-transitions (npz).

        Each file is written under a temporary name and renamed into place. A stream can hold the replay buffer only,
        so with ``absorbing_states`` streams are refused (a ``TypeError``).
        """
        if self.absorbing_transitions is None and not isinstance(path, (str, os.PathLike)):
            super().save_replay_buffer(path)
            return
        buffer_path = replay_buffer_path(path, "DAC.save_replay_buffer", reading=False)
        save_replay_buffer_file(buffer_path, self.replay_buffer)
        if self.absorbing_transitions is not None:
            save_npz(sibling_path(str(buffer_path), ".absorbing.npz"), self.absorbing_transitions.state_dict())

    def load_replay_buffer(self, path: Any, truncate_last_traj: bool = True) -> None:
        """Load what :meth:`save_replay_buffer` wrote; every file is read and checked before anything is replaced."""
        if self.absorbing_transitions is None and not isinstance(path, (str, os.PathLike)):
            self.replay_buffer = read_replay_buffer(path, self, truncate_last_traj)
            return
        buffer_path = replay_buffer_path(path, "DAC.load_replay_buffer", reading=True)
        replay_buffer = read_replay_buffer(buffer_path, self, truncate_last_traj)
        absorbing = None
        if self.absorbing_transitions is not None:
            absorbing_path = sibling_path(str(buffer_path), ".absorbing.npz")
            fix = "save_replay_buffer writes it beside the replay buffer: keep the two together."
            absorbing = read_npz(absorbing_path, "file of absorbing transitions", fix)
            found = {key: value.shape for key, value in absorbing.items()}
            expected = {key: value.shape for key, value in self.absorbing_transitions.state_dict().items()}
            if found != expected:
                raise ValueError(
                    f"The absorbing transitions in {absorbing_path} have shapes {found}, the model's {expected}: were "
                    "they saved by a model with another buffer_size or env?"
                )
        self.replay_buffer = replay_buffer
        if self.absorbing_transitions is not None and absorbing is not None:
            self.absorbing_transitions.load_state_dict(absorbing)
