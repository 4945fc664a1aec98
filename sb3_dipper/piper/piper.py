"""PIPER: HIER whose higher SAC learns from a reward model fitted to primitive-in-the-loop preferences.

Paper: "PIPER: Primitive-Informed Preference-based Hierarchical Reinforcement Learning via Hindsight Relabeling"
(Singh, Suttle, Sadler, Namboodiri, Bedi, ICML 2024); authors' code https://github.com/Utsavz/piper (TF1), from which
DIPPER's preference machinery (:mod:`sb3_dipper.common.preferences`) follows. PIPER changes one thing in HIER: the
higher SAC never learns from the environment's reward. Instead

1. whole higher-level trajectories are paired, with probability ``hindsight_goal_prob`` sharing a goal achieved by one
   of them, and labelled primitive-in-the-loop: ``R(tau) = sum_t 1[ag_{t+1} reached g] + lambda * sum_t V^L(s_t, g_t)``,
   where the second term is the authors' primitive-informed regularisation (``q_reg``: the lower level's value of
   each proposed subgoal; ``value_reg_coef = 0`` is PIPER-No-V);
2. a reward model ``r_phi(s, g, u)`` is fitted to the labels by the Bradley-Terry loss over the summed rewards of the
   two trajectories (:func:`bradley_terry_loss`);
3. the higher SAC trains on its replay buffer with every sampled reward replaced by ``r_phi`` at sampling time
   (:class:`LearnedRewardReplayBuffer`), so a reward is never older than the reward model.

Relabelling with a learned reward: with ``high_her=True`` SB3's HER relabels the goal ``g`` of a share of the sampled
transitions with a goal achieved later in their episode, as HIER does, and their reward is then ``r_phi(s, g', u)`` for
the relabelled goal ``g'``, recomputed by the reward model, not by the environment. Transitions keep their stored goal
otherwise, and get ``r_phi(s, g, u)`` too. With ``high_her=False`` (PIPER as the DIPPER paper ran it, "for fairness")
no goal is relabelled. The preference pairs' own hindsight goal sharing is independent of this switch.

Differences from the authors' code, and why:

- The SAC target uses ``r_phi(s_t, g, u_t)`` of the sampled transition from the current reward model; the authors'
  graph feeds a Polyak-averaged copy of it the *next* state and the policy's next action (a quirk, authors-code.md 5.3).
- ``V^L(s, g) = min_i Q_i(s, g, a) - alpha log pi(a | s, g)`` with ``a ~ pi^L``, as DIPPER's
  ``switch_kwargs["value_reg"] = "score"`` (the authors use ``Q_1`` at a sampled action); at the default
  ``lambda = 1e-6`` either one only breaks ties.
- Q-targets are not clipped to ``[-1 / (1 - gamma), 0]``, as in HIER.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from stable_baselines3 import SAC
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import DictReplayBufferSamples, GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import obs_as_tensor
from stable_baselines3.common.vec_env import VecNormalize
from stable_baselines3.her.her_replay_buffer import HerReplayBuffer

from sb3_dipper.common.hierarchical import sibling_path
from sb3_dipper.common.losses import preference_accuracy, preference_loss, tie_share
from sb3_dipper.common.low_level import sac_state_value
from sb3_dipper.common.option_env import DictObs, low_level_observation
from sb3_dipper.common.preference_pipeline import PreferenceLearner, PreferencePipeline
from sb3_dipper.common.preferences import TrajectoryPairs, TrajectoryPairSampler, flat_pair_observations
from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.common.validation import as_bool, as_float, as_int
from sb3_dipper.hier.hier import HIER
from sb3_dipper.labelling.sources import PreferenceSourceSpec, preference_labeler
from sb3_dipper.piper.policies import RewardModel

SelfPIPER = TypeVar("SelfPIPER", bound="PIPER")


def reward_model_logits(step_rewards: th.Tensor, mask: th.Tensor) -> th.Tensor:
    """The Bradley-Terry logit of each pair, ``z = sum_t r_phi(tau^1_t) - sum_t r_phi(tau^2_t)``, shape ``(B,)``.

    :param step_rewards: ``(2, B, T)`` rewards of the reward model at every step of both trajectories
    :param mask: ``(2, B, T)`` real steps
    """
    returns = (step_rewards * mask.to(step_rewards.dtype)).sum(dim=-1)
    return returns[0] - returns[1]


def bradley_terry_loss(step_rewards: th.Tensor, mask: th.Tensor, labels: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """PIPER's reward-model loss and its logits.

    The softmax cross-entropy over the two trajectories' returns with the label as target distribution (the authors'
    ``ddpg.py``) equals ``-[y log sigma(z) + (1 - y) log sigma(-z)]`` with ``z`` from :func:`reward_model_logits`;
    ``y = 1`` when tau^1 is preferred, 0 when tau^2 is, 0.5 on ties. Averaged over pairs.
    """
    logits = reward_model_logits(step_rewards, mask)
    return preference_loss(logits, labels), logits


class LearnedRewardReplayBuffer(HerReplayBuffer):
    """SB3's ``HerReplayBuffer`` whose sampled rewards are those of a learned reward model, at sampling time.

    Goals are relabelled as SB3's HER does (not at all with ``n_sampled_goal=0``); then every sampled transition, real
    or relabelled, gets ``r_phi(s, g, u)`` for its (possibly relabelled) goal, computed on the observations the sample
    returns (normalised as the learner sees them). The rewards the buffer stores are never used.

    ``reward_model`` is set by the learner before sampling; it is not pickled with the buffer (the model saves it).
    """

    reward_model: RewardModel | None = None

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> DictReplayBufferSamples:  # type: ignore[override]
        samples = super().sample(batch_size, env)
        if self.reward_model is None:
            raise RuntimeError("LearnedRewardReplayBuffer has no reward model: set buffer.reward_model before sampling")
        with th.no_grad():
            rewards = self.reward_model(samples.observations, samples.actions)
        return samples._replace(rewards=rewards.reshape(-1, 1))

    def __getstate__(self) -> dict[str, Any]:
        state = super().__getstate__()
        state.pop("reward_model", None)
        return state


class RewardModelSAC(SAC):
    """SB3's SAC trained on the rewards of a learned reward model: PIPER's higher level.

    It samples from a :class:`LearnedRewardReplayBuffer` (HIER hands every higher SAC a ``HerReplayBuffer``, which is
    swapped for this subclass, so relabelling stays SB3's), and gives it ``reward_model`` before every training round,
    so that a buffer loaded from disk, which comes without it, works as well. The owner sets ``reward_model``.
    """

    reward_model: RewardModel | None = None

    def _setup_model(self) -> None:
        if self.replay_buffer_class is HerReplayBuffer:
            self.replay_buffer_class = LearnedRewardReplayBuffer
        if self.replay_buffer_class is None or not issubclass(self.replay_buffer_class, LearnedRewardReplayBuffer):
            raise ValueError(
                f"RewardModelSAC relabels rewards in a LearnedRewardReplayBuffer, not a {self.replay_buffer_class}: "
                "pass replay_buffer_class=HerReplayBuffer (HIER's) or LearnedRewardReplayBuffer"
            )
        super()._setup_model()

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        buffer = self.replay_buffer
        if not isinstance(buffer, LearnedRewardReplayBuffer):
            raise TypeError(
                f"PIPER's higher SAC needs a LearnedRewardReplayBuffer, but holds a {type(buffer).__name__}: "
                "load a replay buffer saved by PIPER, not by HIER"
            )
        buffer.reward_model = self.reward_model
        super().train(gradient_steps, batch_size)


class PIPER(PreferenceLearner, HIER):
    """PIPER (Singh et al., ICML 2024): HIER whose higher SAC's reward is a reward model learned from PiL preferences.

    The higher SAC (:class:`RewardModelSAC`) trains on ``r_phi(s, g, u)`` in place of the env reward; ``r_phi``
    (:class:`~sb3_dipper.piper.policies.RewardModel`) is fitted by the Bradley-Terry loss (:func:`bradley_terry_loss`)
    to pairs of higher-level trajectories labelled primitive-in-the-loop. Per option, in this order: new labels (the
    dataset grows with training up to ``n_preference_pairs``), ``reward_gradient_steps`` reward-model updates, HIER's
    lower SAC updates, then ``high_gradient_steps`` higher SAC updates. The higher SAC waits for the first labels.

    :param policy: the higher SAC's policy (``"MlpPolicy"`` or ``"MultiInputPolicy"``: SAC's ``MultiInputPolicy``)
    :param env: a goal env with a sparse reward (Dict observations, vectorised ``compute_reward``)
    :param learning_rate: learning rate of the higher SAC
    :param option_steps: K, primitive steps per subgoal
    :param subgoal_space: subgoal space (default: the env's declared one)
    :param value_reg_coef: lambda of the primitive-informed term ``lambda * sum_t V^L(s_t, g_t)`` in the preference
        score (the authors' ``q_reg``, 1e-6 in their code: a tie-breaker); 0 gives PIPER-No-V
    :param n_preference_pairs: the label budget: pairs labelled over the whole run, spread over training
    :param hindsight_goal_prob: probability that both trajectories of a pair share a goal achieved by one of them
    :param trajectory_buffer_size: number of higher-level trajectories kept for pair sampling
    :param preference_source: labels pairs (default: primitive-in-the-loop labels from the env's sparse reward); also
        ``"noisy:P"``, ``"people:DIRECTORY"``, ``"mixed:DIRECTORY:FRACTION"`` or a dict (see
        :func:`~sb3_dipper.labelling.sources.preference_source_from`)
    :param reward_batch_size: pairs per reward-model update (the authors' ``reward_batch_size``, 50)
    :param reward_gradient_steps: reward-model updates per option
    :param reward_learning_rate: learning rate of the reward model
    :param reward_model_kwargs: keyword arguments of the reward model (``net_arch``, ``activation_fn``, ...)
    :param high_her: relabel higher-level goals with HER (the reward of a relabelled transition is ``r_phi`` of the new
        goal); ``False`` runs PIPER as the DIPPER paper did, without HER at the higher level
    :param high_buffer_size: higher replay buffer size (options)
    :param high_batch_size: higher minibatch size
    :param high_gamma: higher discount factor (per option)
    :param high_tau: higher target smoothing coefficient
    :param high_ent_coef: higher entropy coefficient
    :param high_gradient_steps: higher SAC updates per option
    :param high_replay_buffer_kwargs: higher ``HerReplayBuffer`` kwargs (with ``high_her=False``, no ``n_sampled_goal``)
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

    higher_class: ClassVar[type[SAC]] = RewardModelSAC
    higher: RewardModelSAC
    reward_model: RewardModel

    def __init__(
        self,
        policy: str | type[BasePolicy],
        env: GymEnv | str | None,
        learning_rate: float | Schedule = 1e-3,
        option_steps: int = 15,
        subgoal_space: SubgoalSpace | None = None,
        value_reg_coef: float = 1e-6,
        n_preference_pairs: int = 10_000,
        hindsight_goal_prob: float = 0.8,
        trajectory_buffer_size: int = 5000,
        preference_source: PreferenceSourceSpec = None,
        reward_batch_size: int = 50,
        reward_gradient_steps: int = 1,
        reward_learning_rate: float = 1e-3,
        reward_model_kwargs: dict[str, Any] | None = None,
        high_her: bool = True,
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
            high_buffer_size=high_buffer_size,
            high_batch_size=high_batch_size,
            high_gamma=high_gamma,
            high_tau=high_tau,
            high_ent_coef=high_ent_coef,
            high_gradient_steps=high_gradient_steps,
            high_replay_buffer_kwargs=_higher_her_kwargs(high_replay_buffer_kwargs, high_her),
            random_subgoal_prob=random_subgoal_prob,
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
            demo_kwargs=demo_kwargs,
            greedy_episode_prob=greedy_episode_prob,
            max_episode_steps=max_episode_steps,
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            seed=seed,
            device=device,
            _init_setup_model=False,
        )
        self.value_reg_coef = value_reg_coef
        self.n_preference_pairs = n_preference_pairs
        self.hindsight_goal_prob = hindsight_goal_prob
        self.trajectory_buffer_size = trajectory_buffer_size
        self.preference_source = preference_source
        self.reward_batch_size = reward_batch_size
        self.reward_gradient_steps = reward_gradient_steps
        self.reward_learning_rate = reward_learning_rate
        self.reward_model_kwargs = dict(reward_model_kwargs or {})
        self.high_her = high_her
        if _init_setup_model:
            self._setup_model()

    def _check_settings(self) -> None:
        super()._check_settings()
        self.high_her = as_bool("high_her", self.high_her)
        self.hindsight_goal_prob = as_float("hindsight_goal_prob", self.hindsight_goal_prob, 0.0, 1.0)
        self.reward_learning_rate = as_float("reward_learning_rate", self.reward_learning_rate, 0.0, low_open=True)
        self.reward_batch_size = as_int("reward_batch_size", self.reward_batch_size, 1, "pairs per reward-model update")
        self.reward_gradient_steps = as_int("reward_gradient_steps", self.reward_gradient_steps, 0)
        self.value_reg_coef = as_float("value_reg_coef", self.value_reg_coef, 0.0, reason="0 turns the value score off")
        self.n_preference_pairs = as_int("n_preference_pairs", self.n_preference_pairs, 1)
        self.trajectory_buffer_size = as_int(
            "trajectory_buffer_size", self.trajectory_buffer_size, 2, "preference pairs need two stored trajectories"
        )

    def _setup_high_level(self) -> None:
        super()._setup_high_level()
        assert self.subgoal_space is not None
        self.reward_model = RewardModel(
            self.observation_space,  # type: ignore[arg-type]
            self.subgoal_space.unit_box,
            learning_rate=self.reward_learning_rate,
            **self.reward_model_kwargs,
        ).to(self.device)
        self.higher.reward_model = self.reward_model
        labeler = None  # a model without an env labels nothing until it gets one
        if self.env is not None:
            value_score = self._pair_value_score if self.value_reg_coef != 0.0 else None
            labeler = preference_labeler(
                self.preference_source,
                self.env,
                self.subgoal_space,
                self.seed,
                value_score,
                label_budget=self.n_preference_pairs,
            )
        self.preference_pipeline = PreferencePipeline(
            self._higher_level_trajectory_buffer(self.trajectory_buffer_size),
            self.n_preference_pairs,
            TrajectoryPairSampler(self.hindsight_goal_prob, self.subgoal_space),
            labeler,
        )

    def learn(
        self: SelfPIPER,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "PIPER",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfPIPER:
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    def _store_option(
        self,
        start_obs: DictObs,
        high_actions: np.ndarray,
        new_obs: DictObs,
        rewards: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """HIER's higher-level transition, and the same step of the env's current higher-level trajectory."""
        super()._store_option(start_obs, high_actions, new_obs, rewards, dones, infos)
        assert self.option_env is not None and self.option_env.reached_obs is not None
        self.trajectory_buffer.add(start_obs, high_actions, self.option_env.reached_obs["achieved_goal"], dones)

    def _end_open_episodes(self) -> None:
        super()._end_open_episodes()
        self.trajectory_buffer.discard_open()

    # ---------------------------------------------------------------------------------------------------- training

    def train(self) -> None:
        """New labels, reward-model updates on them, then HIER's: the lower SAC and the higher SAC on ``r_phi``."""
        self.preference_pipeline.label_new_pairs(self.num_timesteps, self._total_timesteps, self._rng)
        if len(self.preferences) == 0:
            # Without labels r_phi is an untrained network: its rewards would only teach the higher SAC noise.
            self._train_low_level()
            return
        self._train_reward_model()
        super().train()

    def _train_reward_model(self) -> None:
        """Fit ``r_phi`` to the labelled pairs by the Bradley-Terry loss over the trajectories' summed rewards."""
        self.reward_model.set_training_mode(True)
        losses, accuracies, tie_shares = [], [], []
        for _ in range(self.reward_gradient_steps):
            pairs = self.preferences.sample(self.reward_batch_size, self._rng)
            observations = self._pair_observations(pairs)
            actions = th.as_tensor(pairs.actions.reshape(-1, pairs.actions.shape[-1]), device=self.device)
            mask = th.as_tensor(pairs.mask, device=self.device)
            labels = th.as_tensor(pairs.labels, device=self.device)

            step_rewards = self.reward_model(observations, actions).reshape(mask.shape)
            loss, logits = bradley_terry_loss(step_rewards, mask, labels)
            self.reward_model.optimizer.zero_grad()
            loss.backward()
            self.reward_model.optimizer.step()

            losses.append(loss.item())
            tie_shares.append(tie_share(labels))
            accuracy = preference_accuracy(logits.detach(), labels)
            if accuracy is not None:
                accuracies.append(accuracy)
        self.reward_model.set_training_mode(False)
        self.logger.record("train/high_reward_model_loss", float(np.mean(losses)))
        self.logger.record("train/high_preference_pairs", len(self.preferences))
        self.logger.record("train/high_tie_share", float(np.mean(tie_shares)))
        if accuracies:
            self.logger.record("train/high_reward_model_accuracy", float(np.mean(accuracies)))

    def _pair_observations(self, pairs: TrajectoryPairs) -> dict[str, th.Tensor]:
        """Every step of both trajectories, flattened to ``(2 B T, ...)`` and normalised as the higher SAC sees them."""
        flat_obs = flat_pair_observations(pairs)
        if self._vec_normalize_env is not None:
            flat_obs = self._vec_normalize_env.normalize_obs(flat_obs)  # type: ignore[assignment]
        return obs_as_tensor(flat_obs, self.device)  # type: ignore[return-value]

    def _pair_value_score(self, pairs: TrajectoryPairs) -> np.ndarray:
        """The primitive-informed score term ``lambda * sum_t V^L(s_t, g_t)``, g_t the proposed subgoal, shape ``(2, B)``."""
        assert self.subgoal_space is not None
        flat_obs = flat_pair_observations(pairs)
        subgoals = self.subgoal_space.to_world(pairs.actions.reshape(-1, pairs.actions.shape[-1]))
        low_obs = self.low_level.tensor_obs(low_level_observation(flat_obs, subgoals, self.subgoal_space))
        with th.no_grad():
            values = sac_state_value(self.lower, low_obs).cpu().numpy()
        return self.value_reg_coef * (values.reshape(pairs.mask.shape) * pairs.mask).sum(axis=-1)

    # ---------------------------------------------------------------------------------------------------- saving

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        return [*state_dicts, "reward_model", "reward_model.optimizer"], variables

    def _save_high_level_data(self, path: str) -> None:
        """HIER's higher replay buffer, plus the trajectories and labelled pairs as npz (DIPPER's schema, no pickle)."""
        super()._save_high_level_data(path)
        self.preference_pipeline.save(sibling_path(path, ".high.npz"))

    def _load_high_level_data(self, path: str, truncate_last_traj: bool) -> Callable[[], None]:
        install_higher_buffer = super()._load_high_level_data(path, truncate_last_traj)
        install_preference_data = self.preference_pipeline.read(sibling_path(path, ".high.npz"))

        def install() -> None:
            install_higher_buffer()
            install_preference_data()

        return install


def _higher_her_kwargs(high_replay_buffer_kwargs: dict[str, Any] | None, high_her: bool) -> dict[str, Any]:
    """The higher ``HerReplayBuffer`` kwargs; without HER no transition is relabelled (``n_sampled_goal=0``)."""
    kwargs = {} if high_replay_buffer_kwargs is None else dict(high_replay_buffer_kwargs)
    if high_her:
        return kwargs
    if kwargs.get("n_sampled_goal", 0) != 0:
        raise ValueError(
            f"high_her=False turns HER off at the higher level, but high_replay_buffer_kwargs asks for "
            f"n_sampled_goal={kwargs['n_sampled_goal']}: drop one of the two"
        )
    return {**kwargs, "n_sampled_goal": 0}
