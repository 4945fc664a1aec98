"""The learned lower level: an SB3 ``SAC`` with ``HerReplayBuffer`` on subgoals, driven by the option layer.

The lower SAC never steps an environment itself. It is built on :class:`SubgoalVecEnv`, a facade that exposes the
lower-level goal env (``desired_goal`` = subgoal, vectorised ``compute_reward`` with the subgoal threshold) so that
SB3's ``HerReplayBuffer`` can relabel subgoals; the option layer feeds its buffer and the hierarchical algorithm calls
its ``train()``. Its log keys go through :class:`LevelLogger` so the two levels never overwrite each other.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.vec_env import VecNormalize
from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices

from sb3_dipper.common.option_env import DictObs, LevelVecEnv, PrimitiveTransition
from sb3_dipper.common.subgoals import SubgoalSpace


def low_level_observation_space(observation_space: spaces.Dict, subgoal_space: SubgoalSpace) -> spaces.Dict:
    """``Dict(observation, achieved_goal, desired_goal)`` of the lower level (goals in the subgoal space)."""
    goal_box = spaces.Box(-np.inf, np.inf, shape=(subgoal_space.dim,), dtype=np.float32)
    observation = observation_space["observation"]
    return spaces.Dict(
        {
            "observation": spaces.Box(-np.inf, np.inf, shape=observation.shape, dtype=np.float32),
            "achieved_goal": goal_box,
            "desired_goal": goal_box,
        }
    )


class SubgoalVecEnv(LevelVecEnv):
    """The lower level's goal env as SB3 sees it: spaces and ``compute_reward``, never stepped.

    :param observation_space: the lower-level observation space
    :param action_space: the primitive action space
    :param subgoal_space: gives the subgoal reward
    :param num_envs: number of parallel envs of the option layer
    """

    def __init__(self, observation_space: spaces.Dict, action_space: spaces.Space, subgoal_space: SubgoalSpace, num_envs: int):
        super().__init__(observation_space, action_space, num_envs, level="lower")
        self.subgoal_space = subgoal_space

    def env_method(
        self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **method_kwargs: Any
    ) -> list[Any]:
        if method_name != "compute_reward":
            raise AttributeError(f"The lower level's env only provides compute_reward, not {method_name}")
        return [self.subgoal_space.compute_reward(*method_args, **method_kwargs) for _ in self._get_indices(indices)]


class SubgoalNormalizer:
    """Normalises lower-level observations with the statistics of the base env's ``VecNormalize``.

    ``observation`` uses the base ``observation`` statistics; achieved and desired subgoals use the base
    ``achieved_goal`` statistics of the projected dimensions. It keeps a copy of those statistics (refreshed during
    training), so a saved model can still normalise after ``load(env=None)``, and it offers the two methods SB3's
    buffers call.

    :param subgoal_space: gives the projection of the achieved goal
    """

    def __init__(self, subgoal_space: SubgoalSpace) -> None:
        self.subgoal_space = subgoal_space
        self.statistics: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self.goal_statistics: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self.clip = np.inf
        self.epsilon = 1e-8

    def refresh(self, vec_normalize: VecNormalize) -> None:
        """Copy the current statistics of the base env's ``VecNormalize``."""
        self.statistics, self.goal_statistics = {}, {}
        if not vec_normalize.norm_obs:
            return
        self.clip, self.epsilon = vec_normalize.clip_obs, vec_normalize.epsilon
        for key in ("observation", "achieved_goal", "desired_goal"):
            if key in (vec_normalize.norm_obs_keys or []):
                rms = vec_normalize.obs_rms[key]  # type: ignore[index]
                mean, var = np.array(rms.mean, dtype=np.float64), np.array(rms.var, dtype=np.float64)
                if key != "observation":
                    self.goal_statistics[key] = (mean, var)
                if key == "achieved_goal":
                    mean, var = self.subgoal_space.project(mean), self.subgoal_space.project(var)
                if key != "desired_goal":
                    self.statistics[key] = (mean, var)

    def restore(self, vec_normalize: VecNormalize) -> None:
        """Set the base env's ``VecNormalize`` statistics to this copy (the inverse of :meth:`refresh`): a saved model
        evaluated with the statistics it trained with, not with those of a later save."""
        saved = dict(self.goal_statistics)
        if "observation" in self.statistics:
            saved["observation"] = self.statistics["observation"]
        for key, (mean, var) in saved.items():
            rms = vec_normalize.obs_rms[key]  # type: ignore[index]
            rms.mean, rms.var = mean.copy(), var.copy()

    def _normalize(self, value: np.ndarray, base_key: str) -> np.ndarray:
        if base_key not in self.statistics:
            return value
        mean, var = self.statistics[base_key]
        return np.clip((value - mean) / np.sqrt(var + self.epsilon), -self.clip, self.clip).astype(np.float32)

    def normalize_subgoal(self, subgoals: np.ndarray) -> np.ndarray:
        return self._normalize(subgoals, "achieved_goal")

    def normalize_subgoal_tensor(self, subgoals: th.Tensor) -> th.Tensor:
        """:meth:`normalize_subgoal` for torch tensors, differentiable in ``subgoals``."""
        if "achieved_goal" not in self.statistics:
            return subgoals
        mean, var = (
            th.as_tensor(value, dtype=subgoals.dtype, device=subgoals.device) for value in self.statistics["achieved_goal"]
        )
        return ((subgoals - mean) / th.sqrt(var + self.epsilon)).clamp(-self.clip, self.clip)

    def normalize_obs(self, obs: DictObs) -> DictObs:
        return {
            "observation": self._normalize(obs["observation"], "observation"),
            "achieved_goal": self._normalize(obs["achieved_goal"], "achieved_goal"),
            "desired_goal": self._normalize(obs["desired_goal"], "achieved_goal"),
        }

    def normalize_reward(self, reward: np.ndarray) -> np.ndarray:
        return reward

    def goal_mean_and_std(self, key: str, goal_dim: int) -> tuple[np.ndarray, np.ndarray]:
        """The mean and scale with which a base ``achieved_goal`` or ``desired_goal`` of ``goal_dim`` entries is
        normalised (zeros and ones where it is not): its original value is ``mean + std * normalised``."""
        if key not in self.goal_statistics:
            return np.zeros(goal_dim), np.ones(goal_dim)
        mean, var = self.goal_statistics[key]
        return mean, np.sqrt(var + self.epsilon)

    def unnormalize_goal(self, value: np.ndarray, key: str) -> np.ndarray:
        """Original values of a normalised base ``achieved_goal`` or ``desired_goal``."""
        mean, std = self.goal_mean_and_std(key, np.shape(value)[-1])
        return value * std + mean

    def normalize_goal(self, value: np.ndarray, key: str) -> np.ndarray:
        """Normalise an original base ``achieved_goal`` or ``desired_goal``."""
        if key not in self.goal_statistics:
            return value
        mean, var = self.goal_statistics[key]
        return np.clip((value - mean) / np.sqrt(var + self.epsilon), -self.clip, self.clip).astype(np.float32)


class LevelLogger:
    """Forwards an inner algorithm's log records to the outer logger, renaming ``train/x`` to ``train/<level>_x``."""

    def __init__(self, logger: Logger, level: str) -> None:
        self._logger = logger
        self._level = level

    def _rename(self, key: str) -> str:
        group, _, name = key.partition("/")
        return f"{group}/{self._level}_{name}" if name else f"{self._level}_{key}"

    def record(self, key: str, value: Any, exclude: str | tuple[str, ...] | None = None) -> None:
        self._logger.record(self._rename(key), value, exclude)

    def record_mean(self, key: str, value: Any, exclude: str | tuple[str, ...] | None = None) -> None:
        self._logger.record_mean(self._rename(key), value, exclude)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._logger, name)


def sac_torch_save_params(sac: SAC, prefix: str) -> tuple[list[str], list[str]]:
    """SB3's ``_get_torch_save_params`` of a SAC held as attribute ``prefix`` of an algorithm (state dicts, tensors)."""
    state_dicts = [f"{prefix}.policy", f"{prefix}.actor.optimizer", f"{prefix}.critic.optimizer"]
    if sac.ent_coef_optimizer is not None:
        return [*state_dicts, f"{prefix}.ent_coef_optimizer"], [f"{prefix}.log_ent_coef"]
    return state_dicts, [f"{prefix}.ent_coef_tensor"]


def step_entropy_coefficient(sac: SAC, log_prob: th.Tensor) -> th.Tensor:
    """SAC's entropy coefficient for this gradient step: fixed, or after one step of its own loss when it is learned."""
    if sac.ent_coef_optimizer is None or sac.log_ent_coef is None:
        return sac.ent_coef_tensor
    ent_coef_loss = -(sac.log_ent_coef * (log_prob + float(sac.target_entropy)).detach()).mean()
    sac.ent_coef_optimizer.zero_grad()
    ent_coef_loss.backward()
    sac.ent_coef_optimizer.step()
    return th.exp(sac.log_ent_coef.detach())


def clipped_soft_target(
    rewards: th.Tensor,
    dones: th.Tensor,
    next_q_values: th.Tensor,
    next_log_prob: th.Tensor,
    ent_coef: th.Tensor | float,
    gamma: float,
    bounds: tuple[float, float],
) -> th.Tensor:
    """SAC's soft Bellman target ``r + gamma * (1 - done) * (min Q'(s', a') - alpha * log pi(a' | s'))``, clipped to bounds.

    ``done`` marks transitions without bootstrap (HAC: goal reached or subgoal penalty), not time limits.
    """
    target = rewards + (1.0 - dones) * gamma * (next_q_values - ent_coef * next_log_prob)
    return target.clamp(*bounds)


def sac_state_value(sac: SAC, obs: dict[str, th.Tensor], critic: th.nn.Module | None = None) -> th.Tensor:
    """``V(s, g) = min_i Q_i(s, g, a) - alpha * log pi(a | s, g)``, ``a ~ pi`` (one sample), shape ``(N,)``.

    :param critic: the critic to evaluate (default: the SAC's current critic), for example a snapshot of it
    """
    actions, log_prob = sac.actor.action_log_prob(obs)
    q_values = th.cat((critic or sac.critic)(obs, actions), dim=1).min(dim=1).values
    entropy_coef = th.exp(sac.log_ent_coef.detach()) if sac.log_ent_coef is not None else sac.ent_coef_tensor
    return q_values - entropy_coef * log_prob.reshape(-1)


def sac_value_gap(
    sac: SAC, snapshot_critic: th.nn.Module, obs: dict[str, th.Tensor], noise: th.Tensor | None = None
) -> th.Tensor:
    """``V^L(s, g) - V^L_m(s, g)``: the value under an older critic minus the value under the current one, ``(N,)``.

    Both use one shared action sample of the current lower policy, so the entropy terms of the two values cancel.

    :param noise: the standard normal noise of that sample, ``(N, action_dim)``, as SB3's squashed Gaussian uses it
        (``tanh(mean + noise * std)``); default: SB3's sampler draws it
    """
    if noise is None:
        actions, _ = sac.actor.action_log_prob(obs)
    else:
        mean_actions, log_std, _ = sac.actor.get_action_dist_params(obs)
        actions = th.tanh(mean_actions + noise * log_std.exp())
    old = th.cat(snapshot_critic(obs, actions), dim=1).min(dim=1).values
    new = th.cat(sac.critic(obs, actions), dim=1).min(dim=1).values
    return old - new


def dead_unit_share(network: th.nn.Module, inputs: th.Tensor) -> float | None:
    """The largest share of dead units in one hidden ReLU layer of ``network`` (an ``nn.Sequential``) on ``inputs``.

    A unit is dead on ``inputs`` when it outputs zero for every row. No gradient reaches a dead unit's weights, so it
    stays dead; once a whole layer is dead the network computes the same output for every input (a lower actor that
    acts the same whatever its state and subgoal). ``None`` when ``network`` has no ReLU layer.
    """
    largest: float | None = None
    hidden = inputs
    with th.no_grad():
        for layer in network:  # type: ignore[attr-defined]
            hidden = layer(hidden)
            if isinstance(layer, th.nn.ReLU):
                share = float((hidden <= 0).all(dim=0).float().mean())
                largest = share if largest is None else max(largest, share)
    return largest


def sac_dead_units(sac: SAC, normalizer: SubgoalNormalizer | None = None, n_rows: int = 256) -> dict[str, float]:
    """:func:`dead_unit_share` of the actor and of the first Q-network of ``sac`` on about ``n_rows`` transitions
    spread evenly over its replay buffer, normalised as in training; empty before the buffer holds any.

    Evenly spaced rows draw no random numbers, so logging this leaves training unchanged; spread over the buffer, they
    do not mistake a unit silent on one stretch of similar states (the newest ones, say) for a dead one.
    """
    buffer = sac.replay_buffer
    assert buffer is not None
    stored = buffer.buffer_size if buffer.full else buffer.pos
    if stored == 0:
        return {}
    rows = np.unique(np.linspace(0, stored - 1, -(-n_rows // buffer.n_envs)).round().astype(np.int64))
    observations: DictObs = {
        key: value[rows].reshape(-1, *value.shape[2:])
        for key, value in buffer.observations.items()  # type: ignore[union-attr,attr-defined]
    }
    if normalizer is not None:
        observations = normalizer.normalize_obs(observations)
    obs = {key: th.as_tensor(value, dtype=th.float32, device=sac.device) for key, value in observations.items()}
    actions = th.as_tensor(buffer.actions[rows].reshape(len(rows) * buffer.n_envs, -1), device=sac.device)
    with th.no_grad():
        actor_features = sac.actor.extract_features(obs, sac.actor.features_extractor)
        critic_features = sac.critic.extract_features(obs, sac.critic.features_extractor)
    shares = {
        "actor": dead_unit_share(sac.actor.latent_pi, actor_features),
        "critic": dead_unit_share(sac.critic.q_networks[0], th.cat((critic_features, actions), dim=1)),
    }
    return {name: share for name, share in shares.items() if share is not None}


class SACLowLevel:
    """The option layer's view of a lower SAC: batched actions, values, and the sink that fills its buffer.

    :param sac: the lower-level SAC (its ``env`` is a :class:`SubgoalVecEnv`)
    :param normalizer: normalises lower observations when the base env is a ``VecNormalize``
    """

    def __init__(self, sac: SAC, normalizer: SubgoalNormalizer | None = None) -> None:
        self.sac = sac
        self.normalizer = normalizer
        self.random_actions = False
        # Envs whose lower level acts greedily (its deterministic action) while collecting: HAC's tested subgoals,
        # or the greedy episodes of ``greedy_episode_prob``. None: every env explores.
        self.greedy: np.ndarray | None = None

    def tensor_obs(self, low_obs: DictObs, normalized: bool = False) -> dict[str, th.Tensor]:
        if not normalized and self.normalizer is not None:
            low_obs = self.normalizer.normalize_obs(low_obs)
        return {key: th.as_tensor(value, dtype=th.float32, device=self.sac.device) for key, value in low_obs.items()}

    def normalize_subgoal_tensor(self, subgoals: th.Tensor) -> th.Tensor:
        return subgoals if self.normalizer is None else self.normalizer.normalize_subgoal_tensor(subgoals)

    def act(self, low_obs: DictObs, deterministic: bool, normalized: bool = False) -> np.ndarray:
        """Primitive actions; ``normalized=True`` when ``low_obs`` is already normalised (as in ``predict``)."""
        n_envs = low_obs["desired_goal"].shape[0]
        if self.random_actions:
            scaled = np.random.uniform(-1.0, 1.0, size=(n_envs, get_action_dim(self.sac.action_space))).astype(np.float32)
        else:
            greedy = np.full(n_envs, deterministic) if deterministic or self.greedy is None else self.greedy
            if greedy.all() or not greedy.any():
                scaled = self._scaled_actions(low_obs, bool(greedy.all()), normalized)
            else:
                scaled = self._scaled_actions(low_obs, False, normalized)
                greedy_obs = {key: value[greedy] for key, value in low_obs.items()}
                scaled[greedy] = self._scaled_actions(greedy_obs, True, normalized)
        return self.sac.policy.unscale_action(scaled)

    def _scaled_actions(self, low_obs: DictObs, deterministic: bool, normalized: bool) -> np.ndarray:
        with th.no_grad():
            return self.sac.actor(self.tensor_obs(low_obs, normalized), deterministic=deterministic).cpu().numpy()

    def value(self, low_obs: DictObs) -> np.ndarray | None:
        with th.no_grad():
            return sac_state_value(self.sac, self.tensor_obs(low_obs)).cpu().numpy()

    def store(self, transition: PrimitiveTransition) -> None:
        """Add one primitive step of all envs to the lower HER buffer; a segment end is a truncation."""
        infos = [{"TimeLimit.truncated": bool(end)} for end in transition.segment_ends]
        self.sac.replay_buffer.add(  # type: ignore[union-attr]
            transition.low_obs,  # type: ignore[arg-type]
            transition.next_low_obs,  # type: ignore[arg-type]
            self.sac.policy.scale_action(transition.actions),
            transition.low_rewards,
            transition.segment_ends,
            infos,
        )
