"""Q-filtered behaviour cloning on the lower level from demonstrations (the authors' PIPER code, used by DIPPER).

Each lower-level batch mixes replay transitions with demonstration transitions (a ``demo_share`` of the batch). The
demonstrations are relabelled as the authors' PIPER code relabels its demonstration episode (HER's "future" strategy
over the whole episode, ``future_p = 0.8``): with probability 0.8 the subgoal of a demo step is the achieved subgoal
after a uniformly drawn later step of the same episode (however far), otherwise the demonstration's own goal. Far goals
are what teach the first steps of a demonstration: on pick-and-place the object rests for the first ten steps, so a
goal from the next K steps would pair the approach and the grasp only with "leave the object where it is".
Both parts train the critic; the actor loss is

    rl_coef * mean(alpha * log pi - min_i Q_i(s, pi(s)))  +  bc_coef * sum_{demo, Q-filter} ||mu(s) - a_demo||^2

where ``mu`` is the deterministic action and the Q-filter keeps a demo step only where the first critic values the
demonstrated action above the policy's, ``Q_1(s, a_demo) > Q_1(s, mu(s))`` (Nair et al. 2018; PIPER uses a sum over the
kept demo steps, ``rl_coef = 1e-3`` and a per-task ``bc_coef``).

The flat :class:`~sb3_dipper.sac_demo.SACDemo` clones in the same way, with the env's own goals in place of subgoals
(:class:`EnvGoals`), so that a flat row of a comparison has the hierarchies' demonstrations and cloning.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping
from typing import Any, Protocol

import numpy as np
import torch as th
import torch.nn.functional as F
from stable_baselines3 import SAC
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.common.type_aliases import DictReplayBufferSamples
from stable_baselines3.common.utils import polyak_update

from sb3_dipper.common.demonstrations import Demonstrations
from sb3_dipper.common.low_level import clipped_soft_target, step_entropy_coefficient
from sb3_dipper.common.validation import (
    InvalidSetting,
    as_bool,
    as_demo_path,
    as_float,
    as_optional_int,
    check_dict_keys,
)

# The demonstration settings of a hierarchical algorithm's lower level (its ``demo_kwargs``), with their defaults; SACDemo
# takes them too, but normalize_from_demos.
DEFAULT_DEMO_KWARGS: dict[str, Any] = dict(
    demo_path=None,
    n_demos=None,
    demo_share=0.125,
    bc_coef=0.0078,
    rl_coef=1e-3,
    q_filter=True,
    normalize_from_demos=False,
)


def checked_demo_kwargs(demo_kwargs: Mapping[str, Any], keys: Collection[str] = tuple(DEFAULT_DEMO_KWARGS)) -> dict[str, Any]:
    """``demo_kwargs`` with the defaults (:data:`DEFAULT_DEMO_KWARGS`) of the keys not given, numbers converted
    (``"1e-2"`` from the zoo becomes ``0.01``) and checked: an unknown key is a ``TypeError`` naming the closest
    key, a value out of range an :class:`~sb3_dipper.common.validation.InvalidSetting` naming ``demo_kwargs['key']``.

    :param demo_kwargs: an algorithm's ``demo_kwargs``
    :param keys: the keys the algorithm takes, some of :data:`DEFAULT_DEMO_KWARGS`'s (default: all)
    """
    check_dict_keys("demo_kwargs", demo_kwargs, keys)
    settings = {**{key: DEFAULT_DEMO_KWARGS[key] for key in keys}, **demo_kwargs}
    try:
        settings["n_demos"] = as_optional_int(
            "demo_kwargs['n_demos']", settings["n_demos"], 1, "None: all the episodes demo_path makes"
        )
        settings["demo_share"] = as_float("demo_kwargs['demo_share']", settings["demo_share"], 0.0, 1.0)
        settings["bc_coef"] = as_float("demo_kwargs['bc_coef']", settings["bc_coef"], 0.0, reason="it weighs a loss")
        settings["rl_coef"] = as_float("demo_kwargs['rl_coef']", settings["rl_coef"], 0.0, reason="it weighs a loss")
        settings["q_filter"] = as_bool("demo_kwargs['q_filter']", settings["q_filter"])
        settings["demo_path"] = as_demo_path("demo_kwargs['demo_path']", settings["demo_path"])
        if "normalize_from_demos" in settings:
            settings["normalize_from_demos"] = as_bool("demo_kwargs['normalize_from_demos']", settings["normalize_from_demos"])
    except InvalidSetting as error:
        # The parameter is demo_kwargs: load names it in its advice (load(path, demo_kwargs=...)).
        raise InvalidSetting("demo_kwargs", str(error)) from None
    if settings["demo_path"] is None:
        # Without demonstrations every other setting changes nothing: a bc_coef given with the demo_path forgotten would
        # train without cloning, silently.
        unused = [key for key in keys if key != "demo_path" and settings[key] != DEFAULT_DEMO_KWARGS[key]]
        if unused:
            given = ", ".join(f"demo_kwargs[{key!r}]={settings[key]!r}" for key in unused)
            raise InvalidSetting(
                "demo_kwargs",
                f"{given} without demonstrations changes nothing: give demo_kwargs['demo_path'] too (an npz file, a "
                f"Minari directory, 'auto' or 'auto:dart<N>'), or leave {', '.join(unused)} out",
            )
    return settings


class RelabelledGoals(Protocol):
    """What a :class:`DemonstrationBuffer` needs of the goals it relabels: a
    :class:`~sb3_dipper.common.subgoals.SubgoalSpace` for a lower level, :class:`EnvGoals` for a flat agent."""

    def project(self, achieved_goal: np.ndarray, /) -> np.ndarray:
        """The part of an env's achieved goal that the policy's goals are made of."""

    def compute_reward(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, /) -> np.ndarray:
        """The sparse reward of each row, vectorised over the leading dimensions."""


class EnvGoals:
    """The env's own goals, for a :class:`DemonstrationBuffer` of flat transitions: the whole achieved goal is the goal,
    rewarded as the env rewards it (as SB3's ``HerReplayBuffer`` relabels a flat agent's replay).

    :param env_reward: the env's vectorised ``compute_reward(achieved_goal, desired_goal, infos)``
    """

    def __init__(self, env_reward: Callable[[np.ndarray, np.ndarray, list[dict[str, Any]]], np.ndarray]) -> None:
        self.env_reward = env_reward

    def project(self, achieved_goal: np.ndarray) -> np.ndarray:
        return achieved_goal

    def compute_reward(self, achieved_goal: np.ndarray, desired_goal: np.ndarray) -> np.ndarray:
        infos: list[dict[str, Any]] = [{} for _ in range(achieved_goal.shape[0])]
        return np.asarray(self.env_reward(achieved_goal, desired_goal, infos), dtype=np.float32)


class DemonstrationBuffer:
    """Lower-level transitions of demonstrations, sampled with subgoals relabelled from later in their episode.

    A flat agent's demonstrations are the same transitions with the env's own goals (:class:`EnvGoals`): "subgoal"
    then reads "goal".

    :param demonstrations: the episodes
    :param subgoal_space: projects achieved goals to subgoals and gives the subgoal reward (a
        :class:`~sb3_dipper.common.subgoals.SubgoalSpace`, or :class:`EnvGoals` for the env's own goals)
    :param scaled_actions: the demonstrated actions rescaled to the lower policy's [-1, 1] action space
    :param relabel_prob: probability that a sampled step's subgoal is a later achieved subgoal of its episode instead
        of the demonstration's own goal (PIPER's ``future_p``, 0.8)
    """

    def __init__(
        self,
        demonstrations: Demonstrations,
        subgoal_space: RelabelledGoals,
        scaled_actions: np.ndarray,
        relabel_prob: float = 0.8,
    ):
        self.subgoal_space = subgoal_space
        self.relabel_prob = relabel_prob
        self.observation = demonstrations.observations["observation"].astype(np.float32)
        self.next_observation = demonstrations.next_observations["observation"].astype(np.float32)
        self.achieved = subgoal_space.project(demonstrations.observations["achieved_goal"]).astype(np.float32)
        self.next_achieved = subgoal_space.project(demonstrations.next_observations["achieved_goal"]).astype(np.float32)
        self.desired = subgoal_space.project(demonstrations.observations["desired_goal"]).astype(np.float32)
        self.actions = scaled_actions.astype(np.float32)
        ends = np.cumsum(demonstrations.episode_lengths)
        self.last_step = np.repeat(ends - 1, demonstrations.episode_lengths)

    def __len__(self) -> int:
        return int(self.actions.shape[0])

    def sample(self, batch_size: int) -> tuple[dict[str, np.ndarray], np.ndarray, dict[str, np.ndarray], np.ndarray]:
        """``(observations, actions, next_observations, rewards)`` of ``batch_size`` relabelled demo steps."""
        steps = np.random.randint(len(self), size=batch_size)
        # A later step t' in [t, end of episode], uniformly: its next achieved goal is reached at or after t + 1.
        goal_steps = steps + (np.random.random(batch_size) * (self.last_step[steps] - steps + 1)).astype(np.int64)
        relabel = np.random.random(batch_size) < self.relabel_prob
        goals = np.where(relabel[:, None], self.next_achieved[goal_steps], self.desired[steps])
        observations = {"observation": self.observation[steps], "achieved_goal": self.achieved[steps], "desired_goal": goals}
        next_observations = {
            "observation": self.next_observation[steps],
            "achieved_goal": self.next_achieved[steps],
            "desired_goal": goals,
        }
        rewards = self.subgoal_space.compute_reward(self.next_achieved[steps], goals)
        return observations, self.actions[steps], next_observations, rewards


class DemoSAC(SAC):
    """SB3's SAC whose actor also clones Q-filtered demonstrations (see the module docstring); plain SAC without them.

    :param demonstrations: demo transitions (``None``: this is exactly SB3's SAC)
    :param demo_share: fraction of each batch drawn from the demonstrations
    :param bc_coef: weight of the behaviour-cloning sum (PIPER's lambda_2)
    :param rl_coef: weight of SAC's actor loss when cloning (PIPER's lambda_1)
    :param q_filter: clone only demo steps whose action the critic values above the policy's
    :param target_q_bounds: clip the critic's soft Bellman targets to these bounds (the authors' PIPER code clips every
        level's targets to ``[-1 / (1 - gamma), 0]``, the range of values of a {-1, 0} reward); ``None``: no clip, as SB3
    """

    def __init__(
        self,
        *args: Any,
        demonstrations: DemonstrationBuffer | None = None,
        demo_share: float = 0.125,
        bc_coef: float = 0.0078,
        rl_coef: float = 1e-3,
        q_filter: bool = True,
        target_q_bounds: tuple[float, float] | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(*args, **kwargs)
        if target_q_bounds is not None and not (len(target_q_bounds) == 2 and target_q_bounds[0] < target_q_bounds[1]):
            raise ValueError(f"target_q_bounds must be (low, high) with low < high, got {target_q_bounds!r}")
        self.demonstrations = demonstrations
        self.demo_share = demo_share
        self.bc_coef = bc_coef
        self.rl_coef = rl_coef
        self.q_filter = q_filter
        self.target_q_bounds = None if target_q_bounds is None else (float(target_q_bounds[0]), float(target_q_bounds[1]))

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        if self.demonstrations is None and self.target_q_bounds is None:
            return super().train(gradient_steps, batch_size)
        self.policy.set_training_mode(True)
        optimizers = [self.actor.optimizer, self.critic.optimizer]
        if self.ent_coef_optimizer is not None:
            optimizers.append(self.ent_coef_optimizer)
        self._update_learning_rate(optimizers)
        n_demo = max(1, round(self.demo_share * batch_size)) if self.demonstrations is not None else 0
        bounds = self.target_q_bounds or (-np.inf, np.inf)
        # Per-step values stay tensors until the end: one conversion per logged key instead of one per gradient step.
        log_keys = ("actor_loss", "critic_loss", "ent_coef", "bc_loss", "q_filter_kept")
        logs: dict[str, list[th.Tensor]] = {key: [] for key in log_keys}
        for _ in range(gradient_steps):
            batch = self._mixed_batch(batch_size - n_demo, n_demo)

            # One actor pass: SAC's reparameterised actions and, for cloning, the deterministic actions (the mode).
            mean_actions, log_std, dist_kwargs = self.actor.get_action_dist_params(batch.observations)
            actions_pi, log_prob = self.actor.action_dist.log_prob_from_params(mean_actions, log_std, **dist_kwargs)
            deterministic_actions = self.actor.action_dist.mode()
            log_prob = log_prob.reshape(-1, 1)
            ent_coef = step_entropy_coefficient(self, log_prob)

            # Critic: soft Bellman targets on replay and demo transitions alike.
            with th.no_grad():
                next_actions, next_log_prob = self.actor.action_log_prob(batch.next_observations)
                next_q = (
                    th.cat(self.critic_target(batch.next_observations, next_actions), dim=1).min(dim=1, keepdim=True).values
                )
                target_q = clipped_soft_target(
                    batch.rewards, batch.dones, next_q, next_log_prob.reshape(-1, 1), ent_coef, self.gamma, bounds
                )
            current_q = self.critic(batch.observations, batch.actions)
            critic_loss = 0.5 * sum(F.mse_loss(q, target_q) for q in current_q)
            self.critic.optimizer.zero_grad()
            critic_loss.backward()  # type: ignore[union-attr]
            self.critic.optimizer.step()

            # The actor loss needs the critic's gradient with respect to actions only: with the Q-networks frozen, their
            # weight gradients (which the next critic update would discard) are not computed.
            self._set_q_networks_trainable(False)
            try:
                actor_loss, bc_loss, kept = self._actor_loss(
                    batch, n_demo, actions_pi, log_prob, deterministic_actions, ent_coef
                )
                self.actor.optimizer.zero_grad()
                actor_loss.backward()
            finally:
                self._set_q_networks_trainable(True)
            self.actor.optimizer.step()
            for key, value in zip(log_keys, (actor_loss, critic_loss, ent_coef, bc_loss, kept), strict=True):
                logs[key].append(value.detach())  # type: ignore[union-attr]

            if self._n_updates % self.target_update_interval == 0:
                polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
            self._n_updates += 1
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for key, values in logs.items():
            self.logger.record(f"train/{key}", th.stack(values).float().mean().item())

    def _set_q_networks_trainable(self, trainable: bool) -> None:
        """Switch ``requires_grad`` of the critic's Q-networks (not of a features extractor it may share with the actor)."""
        for q_network in self.critic.q_networks:
            q_network.requires_grad_(trainable)

    def _actor_loss(
        self,
        batch: DictReplayBufferSamples,
        n_demo: int,
        actions_pi: th.Tensor,
        log_prob: th.Tensor,
        deterministic_actions: th.Tensor,
        ent_coef: th.Tensor,
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """``(actor loss, behaviour-cloning sum, kept share of demo steps)``: SAC's actor loss, scaled, plus the
        Q-filtered cloning sum over the batch's last ``n_demo`` rows (the demo steps).

        :param actions_pi: reparameterised actions of the current actor on ``batch.observations``, and ``log_prob``
            their log-probabilities ``(N, 1)``
        :param deterministic_actions: the current actor's deterministic actions on ``batch.observations``
        """
        min_q_pi = th.cat(self.critic(batch.observations, actions_pi), dim=1).min(dim=1, keepdim=True).values
        sac_loss = (ent_coef * log_prob - min_q_pi).mean()
        if n_demo == 0:  # SAC's own actor loss, with the clipped critic
            return sac_loss, sac_loss.new_zeros(()), sac_loss.new_zeros(())
        demo_obs = {key: value[-n_demo:] for key, value in batch.observations.items()}
        demo_actions, policy_actions = batch.actions[-n_demo:], deterministic_actions[-n_demo:]
        keep = (
            q_filter_mask(self.critic, demo_obs, demo_actions, policy_actions)
            if self.q_filter
            else th.ones_like(demo_actions[:, 0])
        )
        bc_loss = behaviour_cloning_loss(policy_actions, demo_actions, keep)
        return self.rl_coef * sac_loss + self.bc_coef * bc_loss, bc_loss, keep.mean()

    def _mixed_batch(self, n_replay: int, n_demo: int) -> DictReplayBufferSamples:
        """Replay transitions followed by ``n_demo`` demo transitions, normalised alike."""
        replay = self.replay_buffer.sample(n_replay, env=self._vec_normalize_env)  # type: ignore[union-attr]
        if n_demo == 0:
            return replay  # type: ignore[return-value]
        observations, actions, next_observations, rewards = self.demonstrations.sample(n_demo)  # type: ignore[union-attr]
        if self._vec_normalize_env is not None:
            observations = self._vec_normalize_env.normalize_obs(observations)  # type: ignore[assignment]
            next_observations = self._vec_normalize_env.normalize_obs(next_observations)  # type: ignore[assignment]
            # As SB3's buffers scale the replay rewards (a flat agent's VecNormalize(norm_reward=True); a lower level's
            # normaliser leaves rewards as they are).
            rewards = self._vec_normalize_env.normalize_reward(rewards)

        def joined(replay_part: dict[str, th.Tensor], demo_part: dict[str, np.ndarray]) -> dict[str, th.Tensor]:
            return {
                key: th.cat((value, th.as_tensor(demo_part[key], device=self.device))) for key, value in replay_part.items()
            }

        return DictReplayBufferSamples(
            observations=joined(replay.observations, observations),  # type: ignore[arg-type]
            actions=th.cat((replay.actions, th.as_tensor(actions, device=self.device))),
            next_observations=joined(replay.next_observations, next_observations),  # type: ignore[arg-type]
            dones=th.cat((replay.dones, th.zeros((n_demo, 1), device=self.device))),
            rewards=th.cat((replay.rewards, th.as_tensor(rewards, device=self.device).reshape(-1, 1))),
        )


def q_filter_mask(
    critic: ContinuousCritic, observations: dict[str, th.Tensor], demo_actions: th.Tensor, policy_actions: th.Tensor
) -> th.Tensor:
    """1 where the first critic values the demonstrated action strictly above the policy's action, else 0 (no gradient).

    Both actions go through the critic in one pass over the observations stacked twice.
    """
    with th.no_grad():
        doubled = {key: th.cat((value, value)) for key, value in observations.items()}
        values = critic.q1_forward(doubled, th.cat((demo_actions, policy_actions))).reshape(2, -1)  # type: ignore[arg-type]
        return (values[0] > values[1]).float()


def behaviour_cloning_loss(policy_actions: th.Tensor, demo_actions: th.Tensor, keep: th.Tensor) -> th.Tensor:
    """``sum_i keep_i * ||policy_action_i - demo_action_i||^2`` (a sum, as in the PIPER code, not a mean)."""
    return (keep * (policy_actions - demo_actions).pow(2).sum(dim=-1)).sum()
