"""SAGA: HIER whose higher policy is also the generator of a subgoal GAN, against a state-conditioned discriminator.

Paper: "State-Conditioned Adversarial Subgoal Generation" (Wang, Pajarinen, Wang, Kämäräinen, AAAI 2023,
https://arxiv.org/abs/2201.09635); released code https://github.com/vi2enne/SAGA (TD3 higher level, HRAC base). The
higher level's subgoals can become infeasible for the lower level as it changes (the non-stationarity of off-policy
HRL). SAGA trains a discriminator ``D(s, g)`` to tell subgoals the lower level *reached* from state ``s`` (relabelled
subgoals) from subgoals the current higher policy *generates* at ``s``, and adds an adversarial term to the higher
actor's loss that pushes its subgoals toward what ``D`` judges reached, i.e. compatible with the current lower level.

Losses (the released code's, binary cross-entropy with a sigmoid ``D``; ``g~`` the relabelled subgoal of an option
that started at ``s``, ``u ~ pi^H(.|s, g*)`` a generated one, all subgoals in the higher level's ``[-1, 1]^d``):

- discriminator (:func:`discriminator_loss`): ``L_D = 1/2 [-log D(s, g~) - log(1 - D(s, u))]``;
- higher actor (:func:`adversarial_loss`): SAC's actor loss ``+ adversarial_coef * L_adv``, ``L_adv = -log D(s, u)``
  (the non-saturating generator loss; the released code weighs it 0.001 beside TD3's ``-Q``).

No gradient penalty: neither the released code nor the reference notes (baselines.md 6) have one.

Choices, and why:

- Relabelled subgoals are the subgoals options actually reached (their end's projected achieved goal), paired with the
  option's start state. The released code uses the stored subgoal, HIRO-corrected for relative goals; with absolute
  subgoals and a learned lower level, the reached subgoal is the one sure to be compatible with the lower level.
- ``state_conditioned=True`` (the paper) gives ``D`` the state (``observation`` and ``achieved_goal``; not the final
  goal, which does not change what the lower level can reach); ``False`` is the released code's ``D(g)``.
- The higher level is SB3's SAC, not TD3: generated subgoals are reparameterised samples of the SAC actor.
- The HRAC adjacency loss and the landmark planner of the released code are not part of the SAGA idea and are left out.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
import torch.nn.functional as F
from stable_baselines3 import SAC
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import obs_as_tensor
from stable_baselines3.her.her_replay_buffer import HerReplayBuffer

from sb3_dipper.common.preferences import relabel_hindsight_actions
from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.common.validation import as_bool, as_float
from sb3_dipper.hier.hier import HIER
from sb3_dipper.saga.policies import SubgoalDiscriminator

SelfSAGA = TypeVar("SelfSAGA", bound="SAGA")


def discriminator_loss(relabelled_logits: th.Tensor, generated_logits: th.Tensor) -> th.Tensor:
    """SAGA's discriminator loss: relabelled subgoals are real (target 1), generated ones fake (target 0).

    ``L_D = 1/2 [BCE(D(s, g~), 1) + BCE(D(s, u), 0)] = 1/2 [-mean log sigma(l~) - mean log(1 - sigma(l))]`` for the
    logits ``l~`` of relabelled and ``l`` of generated subgoals (the released code's ``(real_loss + fake_loss) / 2``).
    """
    real = F.binary_cross_entropy_with_logits(relabelled_logits, th.ones_like(relabelled_logits))
    fake = F.binary_cross_entropy_with_logits(generated_logits, th.zeros_like(generated_logits))
    return 0.5 * (real + fake)


def adversarial_loss(generated_logits: th.Tensor) -> th.Tensor:
    """The generator's (higher actor's) term ``L_adv = BCE(D(s, u), 1) = -mean log sigma(l)``: look reached to ``D``."""
    return F.binary_cross_entropy_with_logits(generated_logits, th.ones_like(generated_logits))


class AdversarialSAC(SAC):
    """SB3's SAC whose actor loss gains one more term: SAGA's higher level, where the actor is also a subgoal generator.

    ``actor_loss_term`` (set by the owner; ``None``: plain SAC) returns a differentiable scalar, here
    ``adversarial_coef * L_adv`` on a batch of states. SB3's ``SAC.train`` builds its actor loss inline; rather than copy
    that method, the term's gradient is added to the actor's gradient just before each actor optimizer step, which is
    exactly a step on ``actor_loss + term``.
    """

    actor_loss_term: Callable[[], th.Tensor] | None = None

    def _setup_model(self) -> None:
        super()._setup_model()
        self.actor.optimizer.register_step_pre_hook(self._add_actor_loss_term)

    def _add_actor_loss_term(self, optimizer: th.optim.Optimizer, args: Any, kwargs: Any) -> None:
        if self.actor_loss_term is not None:
            self.actor_loss_term().backward()


class SAGA(HIER):
    """SAGA (Wang et al., AAAI 2023): HIER plus a discriminator between reached and generated subgoals.

    Per option: ``high_gradient_steps`` discriminator updates (:func:`discriminator_loss`), then HIER's updates: the lower
    SAC, and the higher SAC (:class:`AdversarialSAC`) whose actor loss gains ``adversarial_coef`` times
    :func:`adversarial_loss`. Discriminator and adversarial term each draw ``high_batch_size`` options from the higher
    replay buffer.

    :param policy: the higher SAC's policy (``"MlpPolicy"`` or ``"MultiInputPolicy"``: SAC's ``MultiInputPolicy``)
    :param env: a goal env
    :param learning_rate: learning rate of the higher SAC
    :param option_steps: K, primitive steps per subgoal
    :param subgoal_space: subgoal space (default: the env's declared one)
    :param adversarial_coef: weight of the adversarial term in the higher actor's loss (released code: 0.001)
    :param state_conditioned: ``D(s, g)`` as in the paper; ``False``: the released code's subgoal-only ``D(g)``
    :param discriminator_learning_rate: learning rate of the discriminator (released code: 2e-4)
    :param discriminator_kwargs: keyword arguments of the discriminator (``net_arch``, ``negative_slope``, ...)
    :param high_buffer_size: higher replay buffer size (options)
    :param high_batch_size: higher minibatch size (also of the discriminator and the adversarial term)
    :param high_gamma: higher discount factor (per option)
    :param high_tau: higher target smoothing coefficient
    :param high_ent_coef: higher entropy coefficient
    :param high_gradient_steps: higher SAC and discriminator updates per option
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

    higher_class: ClassVar[type[SAC]] = AdversarialSAC
    higher: AdversarialSAC
    discriminator: SubgoalDiscriminator

    def __init__(
        self,
        policy: str | type[BasePolicy],
        env: GymEnv | str | None,
        learning_rate: float | Schedule = 1e-3,
        option_steps: int = 15,
        subgoal_space: SubgoalSpace | None = None,
        adversarial_coef: float = 0.001,
        state_conditioned: bool = True,
        discriminator_learning_rate: float = 2e-4,
        discriminator_kwargs: dict[str, Any] | None = None,
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
            high_replay_buffer_kwargs=high_replay_buffer_kwargs,
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
        self.adversarial_coef = adversarial_coef
        self.state_conditioned = state_conditioned
        self.discriminator_learning_rate = discriminator_learning_rate
        self.discriminator_kwargs = dict(discriminator_kwargs or {})
        if _init_setup_model:
            self._setup_model()

    def _check_settings(self) -> None:
        super()._check_settings()
        self.state_conditioned = as_bool("state_conditioned", self.state_conditioned)
        self.discriminator_learning_rate = as_float(
            "discriminator_learning_rate", self.discriminator_learning_rate, 0.0, low_open=True
        )
        self.adversarial_coef = as_float(
            "adversarial_coef", self.adversarial_coef, 0.0, reason="it weighs a loss; 0 turns it off"
        )

    def _setup_high_level(self) -> None:
        super()._setup_high_level()
        assert self.subgoal_space is not None
        state_dim = 0
        if self.state_conditioned:
            state_dim = sum(self.observation_space[key].shape[0] for key in ("observation", "achieved_goal"))  # type: ignore[index]
        self.discriminator = SubgoalDiscriminator(
            state_dim, self.subgoal_space.dim, learning_rate=self.discriminator_learning_rate, **self.discriminator_kwargs
        ).to(self.device)
        self.higher.actor_loss_term = self._adversarial_term if self.adversarial_coef > 0.0 else None
        self._adversarial_losses: list[float] = []

    def learn(
        self: SelfSAGA,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "SAGA",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfSAGA:
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    # ---------------------------------------------------------------------------------------------------- training

    def train(self) -> None:
        """The discriminator's updates, then HIER's (the higher actor's loss gains the adversarial term)."""
        self._train_discriminator()
        self._adversarial_losses = []
        super().train()
        if self._adversarial_losses:
            self.logger.record("train/high_adversarial_loss", float(np.mean(self._adversarial_losses)))

    def _train_discriminator(self) -> None:
        """``L_D``: subgoals options reached from ``s`` against subgoals the higher policy generates at ``s``."""
        losses = []
        for _ in range(self.high_gradient_steps):
            observations, relabelled = self._sample_options(self.high_batch_size)
            with th.no_grad():
                generated, _ = self.higher.actor.action_log_prob(observations)
            states = self._discriminator_states(observations)
            loss = discriminator_loss(self.discriminator(states, relabelled), self.discriminator(states, generated))
            self.discriminator.optimizer.zero_grad()
            loss.backward()
            self.discriminator.optimizer.step()
            losses.append(loss.item())
        self.logger.record("train/high_disc_loss", float(np.mean(losses)))

    def _adversarial_term(self) -> th.Tensor:
        """``adversarial_coef * L_adv`` at a fresh batch of option starts, differentiable in the higher actor."""
        observations, _ = self._sample_options(self.high_batch_size)
        generated, _ = self.higher.actor.action_log_prob(observations)
        loss = adversarial_loss(self.discriminator(self._discriminator_states(observations), generated))
        self._adversarial_losses.append(loss.item())
        return self.adversarial_coef * loss

    def _sample_options(self, batch_size: int) -> tuple[dict[str, th.Tensor], th.Tensor]:
        """Start observations of stored options (normalised as the higher policy sees them) and the subgoals they reached.

        Reached subgoals are the projected achieved goals at the options' ends, in the higher level's ``[-1, 1]^d``.
        Only options of finished episodes are drawn, as SB3's HER samples them.
        """
        buffer = self.higher.replay_buffer
        assert isinstance(buffer, HerReplayBuffer) and self.subgoal_space is not None
        finished = np.flatnonzero(buffer.ep_length > 0)
        rows, envs = np.unravel_index(self._rng.choice(finished, size=batch_size), buffer.ep_length.shape)
        observations = {key: value[rows, envs] for key, value in buffer.observations.items()}
        reached = relabel_hindsight_actions(buffer.next_observations["achieved_goal"][rows, envs], self.subgoal_space)
        if self._vec_normalize_env is not None:
            observations = self._vec_normalize_env.normalize_obs(observations)  # type: ignore[assignment]
        return obs_as_tensor(observations, self.device), th.as_tensor(reached, device=self.device)  # type: ignore[return-value]

    def _discriminator_states(self, observations: dict[str, th.Tensor]) -> th.Tensor | None:
        """The state part of the discriminator's input, ``None`` for the subgoal-only ``D(g)``."""
        if not self.state_conditioned:
            return None
        # float(): buffers keep the env's dtype (float64 for PointMaze); SB3's networks cast their inputs the same way.
        return th.cat([observations["observation"], observations["achieved_goal"]], dim=1).float()

    # ---------------------------------------------------------------------------------------------------- saving

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_adversarial_losses"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        return [*state_dicts, "discriminator", "discriminator.optimizer"], variables
