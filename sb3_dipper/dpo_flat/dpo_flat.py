"""DPO-FLAT: one flat policy over primitive actions, trained only by token-level DPO on labelled segment pairs.

The single-level baseline of the DIPPER paper (Singh et al., ICLR 2026, https://arxiv.org/abs/2411.00361): DIPPER's
preference learning without the hierarchy and without the lower-value term. The loss is the token-level DPO of
Rafailov, Hejna, Park, Finn, "From r to Q*: Your Language Model is Secretly a Q-Function" (2024) with a uniform
reference policy, which with segments of equal length is the Contrastive Preference Learning loss (Hejna et al.,
ICLR 2024, https://github.com/jhejna/cpl) with advantage ``beta * log pi``:

    z = beta * sum_t log pi(a^1_t | s^1_t, g) - beta * sum_t log pi(a^2_t | s^2_t, g)
    loss = -[y log sigma(z) + (1 - y) log sigma(-z)]

(``sb3_dipper.common.losses.dipper_loss`` with ``value_reg_coef = 0``; the uniform reference cancels on equal lengths.)

Pairs are CPL-style: two segments of ``segment_length`` primitive steps cut from stored episodes. With probability
``hindsight_goal_prob`` both get one goal, an achieved goal of one of them (PIPER's pair sampling, applied to
segments), and the primitive-in-the-loop labeller prefers the segment with more steps that reach the goal (ties 0.5):
``sb3_dipper.common.preferences``, with a :class:`~sb3_dipper.common.trajectories.TrajectoryBuffer` of primitive steps
whose "actions" are the primitive actions scaled to ``[-1, 1]``. No public code of this baseline exists (the authors'
PIPER code has the analogous RFLAT, a flat SAC on a preference-learned reward).
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv

from sb3_dipper.common.files import replay_buffer_path
from sb3_dipper.common.hierarchical import sibling_path
from sb3_dipper.common.loading import CheckedLoading
from sb3_dipper.common.losses import dipper_loss, preference_accuracy, preferred_nll, tie_share, uniform_log_prob
from sb3_dipper.common.preference_pipeline import PreferenceLearner, PreferencePipeline
from sb3_dipper.common.preferences import PreferenceSource, SegmentPairSampler, TrajectoryPairs, flat_pair_observations
from sb3_dipper.common.preferences import sample_segment_pairs as sample_segment_pairs  # public here first
from sb3_dipper.common.trajectories import TrajectoryBuffer
from sb3_dipper.common.validation import (
    CheckedPredict,
    EnvGoalReward,
    as_float,
    as_int,
    as_optional_int,
    as_train_freq,
    policy_class_and_goal_env,
)
from sb3_dipper.dipper.policies import DIPPERPolicy
from sb3_dipper.dpo_flat.policies import MlpPolicy, MultiInputPolicy
from sb3_dipper.labelling.sources import PreferenceSourceSpec, preference_labeler

SelfDPOFlat = TypeVar("SelfDPOFlat", bound="DPOFlat")

DictObs = dict[str, np.ndarray]

# Episodes a model loaded without an env keeps room for (it only predicts).
PREDICT_ONLY_BUFFER_SIZE = 1


class _TrajectorySink:
    """What SB3's ``_store_transition`` writes to: each primitive step goes to the trajectory buffer.

    SB3 has already found the real next observations (the terminal ones at episode ends, unnormalised).
    """

    def __init__(self, buffer: TrajectoryBuffer) -> None:
        self.buffer = buffer

    def add(
        self,
        obs: DictObs,
        next_obs: DictObs,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        self.buffer.add(obs, action, next_obs["achieved_goal"], done)


class DPOFlat(CheckedPredict, PreferenceLearner, CheckedLoading, OffPolicyAlgorithm):
    """DPO-FLAT (the DIPPER paper's flat baseline): a squashed-Gaussian policy trained only by token-level DPO.

    Collection follows SB3's off-policy loop (``num_timesteps`` counts primitive steps, ``rollout/success_rate`` and
    ``time/*`` as SB3 logs them); every training round labels new segment pairs, up to the share of the label budget
    that the elapsed share of training allows, then takes ``gradient_steps`` DPO steps on ``pairs_per_batch`` pairs.

    :param policy: ``"MlpPolicy"`` or ``"MultiInputPolicy"`` (both :class:`~sb3_dipper.dipper.policies.DIPPERPolicy`)
    :param env: a goal env (Dict observations with ``observation``, ``achieved_goal``, ``desired_goal``) with a sparse
        vectorised ``compute_reward``
    :param learning_rate: learning rate of the policy (DIPPER's higher level and the PIPER code: 1e-3)
    :param segment_length: primitive steps per segment (both segments of a pair have this length)
    :param beta: beta, the weight of the log-likelihoods in the DPO logit
    :param n_preference_pairs: the label budget: pairs labelled over the whole run, spread over training
    :param pairs_per_batch: preference pairs per gradient step
    :param hindsight_goal_prob: probability that both segments of a pair share a goal achieved by one of them
    :param nll_coef: weight of the preferred segment's negative log-likelihood added to the loss (RPO-style; DIPPER: 0)
    :param random_action_prob: probability of a uniformly random action at a step (exploration, on top of the policy's
        own sampling)
    :param trajectory_buffer_size: number of episodes kept for cutting segments
    :param preference_source: labels pairs (default: primitive-in-the-loop labels from the env's sparse reward); also
        ``"noisy:P"``, ``"people:DIRECTORY"``, ``"mixed:DIRECTORY:FRACTION"`` or a dict (see
        :func:`~sb3_dipper.labelling.sources.preference_source_from`)
    :param learning_starts: steps of uniformly random actions before learning
    :param train_freq: train every ``train_freq`` steps (or ``(n, "episode")``)
    :param gradient_steps: DPO gradient steps per training round
    :param max_episode_steps: episode length, the longest episode stored (default: the env's time limit)
    :param policy_kwargs: policy keyword arguments (``net_arch``, ``acting_tau``, ...)
    :param stats_window_size: window of the rollout statistics
    :param tensorboard_log: tensorboard folder
    :param verbose: verbosity
    :param seed: random seed
    :param device: torch device
    :param _init_setup_model: build the networks now
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"MlpPolicy": MlpPolicy, "MultiInputPolicy": MultiInputPolicy}
    policy: DIPPERPolicy

    def __init__(
        self,
        policy: str | type[DIPPERPolicy],
        env: GymEnv | str | None,
        learning_rate: float | Schedule = 1e-3,
        segment_length: int = 25,
        beta: float = 0.1,
        n_preference_pairs: int = 10_000,
        pairs_per_batch: int = 64,
        hindsight_goal_prob: float = 0.8,
        nll_coef: float = 0.0,
        random_action_prob: float = 0.2,
        trajectory_buffer_size: int = 2000,
        preference_source: PreferenceSourceSpec = None,
        learning_starts: int = 1000,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        max_episode_steps: int | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        policy, env = policy_class_and_goal_env(self, policy, env, verbose)
        super().__init__(
            policy,
            env,  # type: ignore[arg-type]
            learning_rate,
            learning_starts=learning_starts,
            batch_size=pairs_per_batch,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            # A copy: the model keeps what it was given, whatever the caller does with the dict afterwards.
            policy_kwargs=dict(policy_kwargs or {}),
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            support_multi_env=True,
            seed=seed,
            sde_support=False,
            supported_action_spaces=(spaces.Box,),
        )
        self.segment_length = segment_length
        self.beta = beta
        self.n_preference_pairs = n_preference_pairs
        self.pairs_per_batch = pairs_per_batch
        self.hindsight_goal_prob = hindsight_goal_prob
        self.nll_coef = nll_coef
        self.random_action_prob = random_action_prob
        self.trajectory_buffer_size = trajectory_buffer_size
        self.preference_source = preference_source
        self.max_episode_steps = max_episode_steps
        self._rng = np.random.default_rng(seed)
        if _init_setup_model:
            self._setup_model()

    def _check_settings(self) -> None:
        super()._check_settings()
        # Settings may arrive as floats or strings (zoo -params, YAML 5e4): coerce or refuse them here, not in training.
        self.segment_length = as_int("segment_length", self.segment_length, 1)
        self.beta = as_float("beta", self.beta, 0.0, low_open=True, reason="beta <= 0 trains toward the rejected segments")
        self.n_preference_pairs = as_int("n_preference_pairs", self.n_preference_pairs, 1)
        self.pairs_per_batch = as_int("pairs_per_batch", self.pairs_per_batch, 1)
        # SB3's learn hands batch_size to train: the pairs of each DPO step.
        self.batch_size = self.pairs_per_batch
        self.nll_coef = as_float("nll_coef", self.nll_coef, 0.0, reason="it weighs a loss; 0 turns it off")
        self.trajectory_buffer_size = as_int("trajectory_buffer_size", self.trajectory_buffer_size, 1)
        self.learning_starts = as_int("learning_starts", self.learning_starts, 0)
        self.train_freq = as_train_freq(self.train_freq)  # type: ignore[assignment]
        self.gradient_steps = as_int("gradient_steps", self.gradient_steps, -1, "-1: as many as environment steps collected")
        self.max_episode_steps = as_optional_int(
            "max_episode_steps", self.max_episode_steps, 1, "None reads the env's time limit"
        )
        self.hindsight_goal_prob = as_float("hindsight_goal_prob", self.hindsight_goal_prob, 0.0, 1.0)
        self.random_action_prob = as_float("random_action_prob", self.random_action_prob, 0.0, 1.0)

    def _setup_model(self) -> None:
        self._check_settings()
        self._setup_lr_schedule()
        self.set_random_seed(self.seed)
        self._convert_train_freq()
        if self.env is not None:
            # Its labeller is built at the first learn; the env's compute_reward is checked now.
            EnvGoalReward(self.env, type(self).__name__)
            self.max_episode_steps = self.max_episode_steps or episode_length(self.env)
        assert self.max_episode_steps is not None, "a saved model always carries its episode length"
        if self.segment_length > self.max_episode_steps:
            raise ValueError(
                f"segment_length ({self.segment_length}) is longer than an episode ({self.max_episode_steps} steps): "
                f"segments are cut from single episodes, so choose segment_length <= {self.max_episode_steps}"
            )
        if self.policy_kwargs.get("goal_anchored"):
            raise ValueError(
                "policy_kwargs goal_anchored=True anchors a higher level's subgoals at the goal; DPO-FLAT's actions are "
                "primitive actions, which have no goal to start from: leave goal_anchored out"
            )
        self.policy = self.policy_class(  # type: ignore[assignment]
            self.observation_space, self.action_space, self.lr_schedule, **self.policy_kwargs
        ).to(self.device)
        # A model loaded without an env only predicts: its episode store stays tiny until it gets an env to learn on,
        # and its labeller comes with the first learn (or load_replay_buffer).
        self.preference_pipeline = PreferencePipeline(
            self._make_trajectory_buffer(self.trajectory_buffer_size if self.env is not None else PREDICT_ONLY_BUFFER_SIZE),
            self.n_preference_pairs,
            SegmentPairSampler(self.segment_length, self.hindsight_goal_prob),
        )
        self._reference_log_prob = uniform_log_prob(int(np.prod(self.action_space.shape)))  # type: ignore[arg-type]

    def _ensure_full_trajectory_buffer(self) -> None:
        """A model loaded without an env gets its full-size episode store once it is to learn or load episodes."""
        if self.trajectory_buffer.capacity != self.trajectory_buffer_size:
            self.trajectory_buffer = self._make_trajectory_buffer(self.trajectory_buffer_size)

    def _make_trajectory_buffer(self, capacity: int) -> TrajectoryBuffer:
        assert self.max_episode_steps is not None
        return TrajectoryBuffer(
            capacity,
            self.max_episode_steps,
            self.observation_space,  # type: ignore[arg-type]
            int(np.prod(self.action_space.shape)),  # type: ignore[arg-type]
            self.n_envs,
        )

    def learn(
        self: SelfDPOFlat,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "DPOFlat",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfDPOFlat:
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> Any:
        self._ensure_full_trajectory_buffer()
        if reset_num_timesteps or self._last_obs is None:
            # The env is about to be reset: an episode a callback interrupted must not run on into the new one.
            self.trajectory_buffer.discard_open()
        if self.preference_pipeline.labeler is None:
            self.preference_pipeline.labeler = self._new_labeler()
        return super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)

    def _new_labeler(self) -> PreferenceSource:
        assert self.env is not None
        return preference_labeler(self.preference_source, self.env, None, self.seed, label_budget=self.n_preference_pairs)

    # ---------------------------------------------------------------------------------------------------- acting

    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """The policy's sampled action (uniform before ``learning_starts``), uniform with ``random_action_prob``."""
        action, buffer_action = super()._sample_action(learning_starts, action_noise, n_envs)
        explore = self._rng.random(n_envs) < self.random_action_prob
        if explore.any():
            buffer_action = np.array(buffer_action, dtype=np.float32)
            buffer_action[explore] = self._rng.uniform(-1.0, 1.0, size=(int(explore.sum()), buffer_action.shape[1]))
            action = self.policy.unscale_action(buffer_action)
        return action, buffer_action

    def _store_transition(
        self,
        replay_buffer: ReplayBuffer | None,
        buffer_action: np.ndarray,
        new_obs: np.ndarray | dict[str, np.ndarray],
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """SB3's storing (terminal observations, unnormalised), into the trajectory buffer: there is no replay buffer."""
        sink = _TrajectorySink(self.trajectory_buffer)
        super()._store_transition(sink, buffer_action, new_obs, reward, dones, infos)  # type: ignore[arg-type]

    # ---------------------------------------------------------------------------------------------------- training

    def train(self, gradient_steps: int, batch_size: int) -> None:
        """New labels, then ``gradient_steps`` DPO steps on ``batch_size`` pairs each."""
        self.preference_pipeline.label_new_pairs(self.num_timesteps, self._total_timesteps, self._rng)
        if len(self.preferences) == 0:
            return
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.actor.optimizer)
        logs: dict[str, list[float]] = defaultdict(list)
        for _ in range(gradient_steps):
            pairs = self.preferences.sample(batch_size, self._rng)
            observations, actions, mask, labels = self._pair_tensors(pairs)

            # Token-level DPO with a uniform reference: DIPPER's loss (Eq. 9) without the value term, on primitive actions.
            log_probs = self.policy.log_prob(observations, actions).reshape(mask.shape)
            dpo, logits = dipper_loss(log_probs, mask, labels, self.beta, self._reference_log_prob)
            loss = dpo

            # Optional: the preferred segment's likelihood (RPO-style), against likelihood displacement.
            if self.nll_coef > 0.0:
                nll = preferred_nll(log_probs, mask, labels)
                loss = loss + self.nll_coef * nll
                logs["nll"].append(nll.item())

            self.policy.actor.optimizer.zero_grad()
            loss.backward()
            self.policy.actor.optimizer.step()
            self.policy.update_averaged_actor()

            logs["dpo_loss"].append(dpo.item())
            logs["tie_share"].append(tie_share(labels))
            accuracy = preference_accuracy(logits.detach(), labels)
            if accuracy is not None:
                logs["pref_accuracy"].append(accuracy)
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/preference_pairs", len(self.preferences))
        for key, values in logs.items():
            self.logger.record(f"train/{key}", float(np.mean(values)))

    def _pair_tensors(self, pairs: TrajectoryPairs) -> tuple[dict[str, th.Tensor], th.Tensor, th.Tensor, th.Tensor]:
        """Every step of both segments as one batch: (normalised) observations and actions, plus the mask and labels."""
        flat_obs = flat_pair_observations(pairs)
        if self._vec_normalize_env is not None:
            flat_obs = self._vec_normalize_env.normalize_obs(flat_obs)  # type: ignore[assignment]
        observations = obs_as_tensor(flat_obs, self.device)  # type: ignore[arg-type]
        actions = th.as_tensor(pairs.actions.reshape(-1, pairs.actions.shape[-1]), device=self.device)
        mask = th.as_tensor(pairs.mask, device=self.device)
        labels = th.as_tensor(pairs.labels, device=self.device)
        return observations, actions, mask, labels  # type: ignore[return-value]

    # ---------------------------------------------------------------------------------------------------- saving

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        return ["policy", "policy.actor.optimizer"], []

    def save_replay_buffer(self, path: Any) -> None:
        """The stored episodes and labelled pairs, as npz (read without pickle) beside ``path`` (``x.pkl`` -> ``x.npz``).

        The file is written under a temporary name and renamed into place. Streams are refused (a ``TypeError``).
        """
        path = replay_buffer_path(path, "DPOFlat.save_replay_buffer", reading=False)
        self.preference_pipeline.save(sibling_path(str(path), ".npz"))

    def load_replay_buffer(self, path: Any, truncate_last_traj: bool = True) -> None:
        """Load what :meth:`save_replay_buffer` wrote, to resume training where it stopped.

        The file is read and checked against the model first: on an error (naming the file) nothing is replaced.
        """
        path = replay_buffer_path(path, "DPOFlat.load_replay_buffer", reading=True)
        self._ensure_full_trajectory_buffer()
        if self.preference_pipeline.labeler is None and self.env is not None:
            self.preference_pipeline.labeler = self._new_labeler()
        self.preference_pipeline.load(sibling_path(str(path), ".npz"))


def episode_length(env: VecEnv) -> int:
    """The env's time limit (``spec.max_episode_steps``), or a clear error if it has none."""
    spec = env.get_attr("spec", indices=[0])[0]
    length = getattr(spec, "max_episode_steps", None)
    if length is None:
        raise ValueError(
            "The env has no time limit (spec.max_episode_steps is None): DPOFlat stores whole episodes and needs their "
            "length. Pass max_episode_steps=... or wrap the env in TimeLimit."
        )
    return int(length)
