"""HAC: Hierarchical Actor-Critic (Levy, Konidaris, Platt, Saenko, "Learning Multi-Level Hierarchies with Hindsight",
ICLR 2019, https://arxiv.org/abs/1712.00948; official code https://github.com/andrew-j-levy/Hierarchical-Actor-Critc-HAC-).

Two levels on the shared option layer. The higher level is a SAC (as in the DIPPER authors' baselines) over subgoals
in ``[-1, 1]^d`` that learns from HAC's three kinds of transitions (rules in :mod:`sb3_dipper.hac.hindsight`):
hindsight actions, hindsight goals and subgoal-testing penalties. It keeps its own plain ``DictReplayBuffer``: SB3's
``HerReplayBuffer`` relabels "future" goals and keeps ``done``, while HAC relabels whole windows and recomputes
``done`` (a reached goal ends bootstrapping). Its critic targets are clipped to ``[-T, 0]`` (HAC's ``critic.py``), ``T``
(``high_steps``) being its horizon: the options of one base episode.

The lower level is the shared SAC+HER on subgoals: it also gets hindsight goals, from SB3's HER ("future" goals within
each K-step segment, where HAC relabels the lower window "episode"-style). Its targets are not clipped: HAC bounds a
level's values by its horizon because a level's episode is its ``H`` attempts and ends when the goal is reached, but
the shared lower level bootstraps across segment ends and does not stop at its subgoal, so its values go down to
``-1 / (1 - gamma)``, below ``-K`` for the default ``gamma = 0.95`` and ``K = 15``.

Choices where the paper leaves room or our setting differs:

- Hindsight goals: the last achieved goal of the window and ``n_hindsight_goals - 1`` uniformly drawn ones, each
  relabelling every transition of the window (HAC's ``finalize_goal_replay``; 3 goals as in its root code).
- Subgoal testing starts with learning (``learning_starts``): before it both levels act uniformly at random.
  Whether a subgoal is tested is drawn per env and per option; a tested env's lower level acts deterministically.
- HAC gives every level one horizon ``H`` (its attempts per goal) and bounds a level's critic to ``[-H, 0]`` and its
  penalty for a missed subgoal to ``-H`` with that level's own ``H`` (``layer.py``, ``critic.py``). Here the levels'
  horizons differ, so the higher level's bound and penalty use its horizon ``T = high_steps``, not the lower level's
  ``K = option_steps`` (the DIPPER tasks have ``K = T``; ``PointMazeFourRooms-v0`` in our zoo has ``K = 20``, ``T = 10``).
- SAC with target networks and an entropy bonus replaces HAC's DDPG without target networks.
- A subgoal counts as reached if it is reached at the end of its option: the shared option layer always runs K steps,
  where HAC's lower level hands control back as soon as it reaches its subgoal.

``paper_compat`` follows the authors' intent where their code (``rollout.py``, ``her.py``) departs from it: their
hindsight action is the achieved goal at the option's *start* (read before it is updated), and their HER sampler
recomputes every sampled reward from the goals, so the stored ``-T`` never reaches a target. Here the hindsight action
is the reached subgoal and ``-T`` is kept on the greedy episode's unrelabelled copy. The greedy episode's relabelled
copies are not stored: with recomputed rewards they repeat the plain episode's.
"""

from __future__ import annotations

from collections import deque
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
import torch.nn.functional as F
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import DictReplayBuffer
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import polyak_update

from sb3_dipper.common.hierarchical import has_finished_episode
from sb3_dipper.common.low_level import clipped_soft_target, step_entropy_coefficient
from sb3_dipper.common.option_env import DictObs
from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.common.validation import as_bool, as_float, as_int, sparse_goal_reached_fn
from sb3_dipper.hac.hindsight import (
    future_goal_pairs,
    goal_rewards,
    greedy_episode_rewards,
    hac_goal_indices,
    hac_goal_pairs,
    hindsight_actions,
    penalized_subgoals,
    penalty_transitions,
    relabel_goals,
)
from sb3_dipper.hac.policies import MlpPolicy, MultiInputPolicy
from sb3_dipper.hier.hier import HIER, OptionGoalVecEnv

SelfHAC = TypeVar("SelfHAC", bound="HAC")


class ClippedSAC(SAC):
    """SB3's SAC whose critic targets are clipped to ``target_q_bounds`` (HAC's bounded values; the PIPER code's clip).

    :param target_q_bounds: ``(low, high)`` of the soft Bellman targets
    """

    def __init__(self, *args: Any, target_q_bounds: tuple[float, float] = (-np.inf, np.inf), **kwargs: Any) -> None:
        self.target_q_bounds = target_q_bounds
        super().__init__(*args, **kwargs)

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """SAC's updates (entropy coefficient, critic, actor, target networks) with the clipped critic target."""
        self.policy.set_training_mode(True)
        optimizers = [self.actor.optimizer, self.critic.optimizer]
        if self.ent_coef_optimizer is not None:
            optimizers.append(self.ent_coef_optimizer)
        self._update_learning_rate(optimizers)
        logs: dict[str, list[float]] = {"ent_coef": [], "actor_loss": [], "critic_loss": [], "target_q": []}
        for _ in range(gradient_steps):
            batch = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]

            # Entropy coefficient (SAC).
            actions_pi, log_prob = self.actor.action_log_prob(batch.observations)
            log_prob = log_prob.reshape(-1, 1)
            ent_coef = step_entropy_coefficient(self, log_prob)
            logs["ent_coef"].append(ent_coef.item())

            # Critic: no bootstrap where done, target clipped (HAC critic.py).
            with th.no_grad():
                next_actions, next_log_prob = self.actor.action_log_prob(batch.next_observations)
                next_q = (
                    th.cat(self.critic_target(batch.next_observations, next_actions), dim=1).min(dim=1, keepdim=True).values
                )
                target_q = clipped_soft_target(
                    batch.rewards,
                    batch.dones,
                    next_q,
                    next_log_prob.reshape(-1, 1),
                    ent_coef,
                    self.gamma,
                    self.target_q_bounds,
                )
            current_q = self.critic(batch.observations, batch.actions)
            critic_loss = 0.5 * sum(F.mse_loss(q, target_q) for q in current_q)
            self.critic.optimizer.zero_grad()
            critic_loss.backward()  # type: ignore[union-attr]
            self.critic.optimizer.step()
            logs["critic_loss"].append(critic_loss.item())  # type: ignore[union-attr]
            logs["target_q"].append(target_q.mean().item())

            # Actor (SAC).
            min_q_pi = th.cat(self.critic(batch.observations, actions_pi), dim=1).min(dim=1, keepdim=True).values
            actor_loss = (ent_coef * log_prob - min_q_pi).mean()
            self.actor.optimizer.zero_grad()
            actor_loss.backward()
            self.actor.optimizer.step()
            logs["actor_loss"].append(actor_loss.item())

            if self._n_updates % self.target_update_interval == 0:
                polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
                polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)
            self._n_updates += 1
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for key, values in logs.items():
            self.logger.record(f"train/{key}", float(np.mean(values)))


class EpisodeWindows:
    """Each env's options of the current episode, kept for hindsight goals at its end.

    An option is stored with its ``(S, d)`` streams of actions: one per copy of the transition that gets relabelled.

    :param n_envs: number of envs
    """

    def __init__(self, n_envs: int) -> None:
        self._steps: list[list[tuple[DictObs, np.ndarray, DictObs]]] = [[] for _ in range(n_envs)]

    def add(self, env: int, observation: DictObs, actions: np.ndarray, next_observation: DictObs) -> None:
        self._steps[env].append((observation, actions, next_observation))

    def open_envs(self) -> list[int]:
        return [env for env, steps in enumerate(self._steps) if steps]

    def pop(self, env: int) -> tuple[DictObs, np.ndarray, DictObs]:
        """``(observations, actions (T, S, d), next_observations)`` of the env's window, stacked over options; empties it."""
        steps, self._steps[env] = self._steps[env], []
        observations, actions, next_observations = zip(*steps, strict=True)
        return _stack(observations), np.stack(actions), _stack(next_observations)


def _stack(observations: tuple[DictObs, ...]) -> DictObs:
    return {key: np.stack([observation[key] for observation in observations]) for key in observations[0]}


def _rows(observation: DictObs, rows: np.ndarray | int | slice) -> DictObs:
    return {key: value[rows] for key, value in observation.items()}


def _with_goals(observation: DictObs, goals: np.ndarray) -> DictObs:
    return {**observation, "desired_goal": goals}


class HAC(HIER):
    """HAC (Levy et al., ICLR 2019) with two levels: hindsight action and goal transitions, subgoal testing, clipped Q.

    The higher level is a :class:`ClippedSAC` on a plain ``DictReplayBuffer`` filled by the rules of
    :mod:`sb3_dipper.hac.hindsight`; the lower level is the shared SAC+HER (see the module docstring). Per option:

    - the hindsight action transition ``(s_t, u_t or p(s_{t+1}), r, s_{t+1}, g*)``, ``r = -1`` or 0 with ``done`` when
      ``g*`` is reached (Section 4.2);
    - with probability ``subgoal_test_prob`` the subgoal is tested: the lower level acts greedily and, if it misses,
      ``(s_t, u_t, -T, s_{t+1}, g*)`` with ``done`` (Section 4.4; ``T``, the higher level's horizon, is ``high_steps``);

    and when the episode ends, hindsight goal transitions of the whole window (Section 4.3).
    ``paper_compat=True`` is the DIPPER authors' simplified HAC (their PIPER code, ``--hac=1``): every option is stored
    with the proposed subgoal (HIER's transition) and with the reached one (hindsight action), every
    ``greedy_episode_interval``-th episode runs a greedy lower level and stores its options once more with reward ``-T``
    (no test of whether the subgoal was missed), goals are relabelled with HER's "future" strategy, nothing terminates
    and targets are clipped to ``[-1 / (1 - gamma), 0]``.

    :param policy: the higher SAC's policy (``"MlpPolicy"`` or ``"MultiInputPolicy"``: SAC's ``MultiInputPolicy``)
    :param env: a goal env with a sparse reward
    :param learning_rate: learning rate of the higher SAC
    :param option_steps: K, primitive steps per subgoal; the higher level's horizon is ``T = ceil(episode length / K)``
        options, which sets its subgoal penalty ``-T`` and its critic bound ``[-T, 0]``
    :param subgoal_space: subgoal space (default: the env's declared one)
    :param subgoal_test_prob: HAC's lambda, the probability that a proposed subgoal is tested
    :param n_hindsight_goals: goals relabelling each window (HAC, default 3), or "future" goals per transition
        (``paper_compat``, default 4 as the authors' HER)
    :param paper_compat: the DIPPER authors' simplified HAC instead of the paper's
    :param greedy_episode_interval: with ``paper_compat``, every this-many-th episode of an env is greedy
    :param high_buffer_size: higher replay buffer size (transitions)
    :param high_batch_size: higher minibatch size
    :param high_gamma: higher discount factor (per option)
    :param high_tau: higher target smoothing coefficient
    :param high_ent_coef: higher entropy coefficient
    :param high_gradient_steps: higher gradient steps per option
    :param random_subgoal_prob: probability of a uniformly random subgoal during training (HAC: 20 % random actions)
    :param buffer_size: lower replay buffer size
    :param learning_starts: primitive steps of random subgoals and lower actions before learning (and testing)
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
    higher: ClippedSAC

    def __init__(
        self,
        policy: str | type[BasePolicy],
        env: GymEnv | str | None,
        learning_rate: float | Schedule = 1e-3,
        option_steps: int = 15,
        subgoal_space: SubgoalSpace | None = None,
        subgoal_test_prob: float = 0.3,
        n_hindsight_goals: int | None = None,
        paper_compat: bool = False,
        greedy_episode_interval: int = 3,
        high_buffer_size: int = 1_000_000,
        high_batch_size: int = 256,
        high_gamma: float = 0.95,
        high_tau: float = 0.005,
        high_ent_coef: str | float = "auto",
        high_gradient_steps: int = 1,
        random_subgoal_prob: float = 0.2,
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
            max_episode_steps=max_episode_steps,
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            seed=seed,
            device=device,
            _init_setup_model=False,
        )
        self.subgoal_test_prob = subgoal_test_prob
        self.paper_compat = paper_compat
        self.n_hindsight_goals = n_hindsight_goals if n_hindsight_goals is not None else (4 if paper_compat else 3)
        self.greedy_episode_interval = greedy_episode_interval
        if _init_setup_model:
            self._setup_model()

    # ---------------------------------------------------------------------------------------------------- set-up

    def _check_settings(self) -> None:
        super()._check_settings()
        self.paper_compat = as_bool("paper_compat", self.paper_compat)
        self.subgoal_test_prob = as_float("subgoal_test_prob", self.subgoal_test_prob, 0.0, 1.0)
        self.n_hindsight_goals = as_int("n_hindsight_goals", self.n_hindsight_goals, 0)
        self.greedy_episode_interval = as_int("greedy_episode_interval", self.greedy_episode_interval, 1)

    @property
    def target_q_bounds(self) -> tuple[float, float]:
        """HAC: ``[-T, 0]``, the higher level's horizon; the DIPPER authors: ``[-1 / (1 - gamma), 0]``."""
        if self.paper_compat:
            return -1.0 / (1.0 - self.high_gamma), 0.0
        return -float(self.high_steps), 0.0

    def _setup_high_level(self) -> None:
        assert self.subgoal_space is not None
        # One buffer row per relabelled transition, however many an option yields: the buffer is built for one env.
        high_env = OptionGoalVecEnv(self.observation_space, self.subgoal_space.unit_box, self.env, num_envs=1)  # type: ignore[arg-type]
        self.higher = ClippedSAC(
            self.policy_class,  # type: ignore[arg-type]
            high_env,
            learning_rate=self.learning_rate,
            buffer_size=self.high_buffer_size if self.env is not None else 16,
            learning_starts=0,
            batch_size=self.high_batch_size,
            tau=self.high_tau,
            gamma=self.high_gamma,
            ent_coef=self.high_ent_coef,
            replay_buffer_class=DictReplayBuffer,
            # A copy: SB3's SAC adds use_sde to the policy_kwargs it is handed.
            policy_kwargs=dict(self.policy_kwargs),
            device=self.device,
            target_q_bounds=self.target_q_bounds,
        )
        self.higher._vec_normalize_env = self._vec_normalize_env
        self.policy = self.higher.policy
        self._windows = EpisodeWindows(self.n_envs)
        self._episode_counts = np.zeros(self.n_envs, dtype=np.int64)
        if self.env is not None:
            self._goal_reached = sparse_goal_reached_fn(self.env, type(self).__name__)

    def learn(
        self: SelfHAC,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "HAC",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfHAC:
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    def _setup_learn(self, *args: Any, **kwargs: Any) -> Any:
        result = super()._setup_learn(*args, **kwargs)
        self._option_metrics["tested_subgoal_missed"] = deque(maxlen=self._stats_window_size)
        return result

    # ---------------------------------------------------------------------------------------------------- acting

    def _training_high_level_actions(self, observation: DictObs) -> np.ndarray:
        """The subgoals to propose, and which of them to test (the lower level then acts greedily on them)."""
        actions = super()._training_high_level_actions(observation)
        self.low_level.greedy = self._greedy_options()
        return actions

    def _greedy_options(self) -> np.ndarray:
        """Envs whose lower level acts greedily this option: tested subgoals, or the authors' greedy episodes."""
        if self.num_timesteps < self.learning_starts:
            return np.zeros(self.n_envs, dtype=bool)
        if self.paper_compat:
            return self._episode_counts % self.greedy_episode_interval == 0
        return self._rng.random(self.n_envs) < self.subgoal_test_prob

    # ---------------------------------------------------------------------------------------------------- storing

    def _store_option(
        self,
        start_obs: DictObs,
        high_actions: np.ndarray,
        new_obs: DictObs,
        rewards: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """Hindsight action and penalty transitions now; hindsight goal transitions of envs whose episode ended."""
        assert self.option_env is not None and self.option_env.reached_obs is not None and self.subgoal_space is not None
        space, reached_obs = self.subgoal_space, self.option_env.reached_obs
        achieved = np.stack([info["achieved_subgoal"] for info in infos])
        subgoal_reached = space.compute_reward(achieved, space.to_world(high_actions)) == 0.0
        greedy = self.low_level.greedy
        assert greedy is not None, "set with the option's subgoals"
        goal_reward, goal_done = goal_rewards(reached_obs["achieved_goal"], start_obs["desired_goal"], self._goal_reached)
        done = self._bootstrap_flags(goal_done)

        if self.paper_compat:
            # The authors store three episodes: the plain one, its hindsight-action copy (always the reached subgoal),
            # and in greedy episodes the plain one again with -T on every transition.
            streams = np.stack([high_actions, hindsight_actions(high_actions, space.to_unit(achieved), np.zeros_like(greedy))])
            if greedy.any():
                self._add_transitions(
                    _rows(start_obs, greedy),
                    high_actions[greedy],
                    greedy_episode_rewards(int(greedy.sum()), self.high_steps),
                    _rows(reached_obs, greedy),
                    np.zeros(int(greedy.sum()), dtype=np.float32),
                )
        else:
            # Section 4.2: the subgoal actually reached replaces a missed one.
            streams = hindsight_actions(high_actions, space.to_unit(achieved), subgoal_reached)[None]
            # Section 4.4: a tested subgoal the greedy lower level missed in its K steps is penalised, without bootstrap,
            # with the proposing level's lowest value -T.
            completed = np.array([info["option_steps"] == self.option_steps for info in infos])
            penalized = penalized_subgoals(greedy, subgoal_reached, completed)
            if penalized.any():
                penalty_reward, penalty_done = penalty_transitions(int(penalized.sum()), self.high_steps)
                self._add_transitions(
                    _rows(start_obs, penalized),
                    high_actions[penalized],
                    penalty_reward,
                    _rows(reached_obs, penalized),
                    penalty_done,
                )
            self._option_metrics["tested_subgoal_missed"].extend(penalized[greedy & completed].astype(float))
        for actions in streams:
            self._add_transitions(start_obs, actions, goal_reward, reached_obs, done)

        # Section 4.3: the window waits for the end of its episode.
        for env in range(self.n_envs):
            self._windows.add(env, _rows(start_obs, env), streams[:, env], _rows(reached_obs, env))
        for ended in np.flatnonzero(dones):
            self._store_hindsight_goals(int(ended))
        self._episode_counts += dones.astype(np.int64)

    def _store_hindsight_goals(self, env: int) -> None:
        """Relabel the env's window with achieved goals (HAC: whole window per goal; the authors: HER's "future").

        Each stream of actions (HAC: the hindsight actions; the authors: plain and hindsight actions) is relabelled.
        """
        observations, streams, next_observations = self._windows.pop(env)
        n_transitions = streams.shape[0]
        for stream in range(streams.shape[1]):
            if self.paper_compat:
                transitions, goal_indices = future_goal_pairs(n_transitions, self.n_hindsight_goals, self._rng)
            else:
                transitions, goal_indices = hac_goal_pairs(
                    n_transitions, hac_goal_indices(n_transitions, self.n_hindsight_goals, self._rng)
                )
            goals, rewards, dones = relabel_goals(
                next_observations["achieved_goal"], transitions, goal_indices, self._goal_reached
            )
            self._add_transitions(
                _with_goals(_rows(observations, transitions), goals),
                streams[transitions, stream],
                rewards,
                _with_goals(_rows(next_observations, transitions), goals),
                self._bootstrap_flags(dones),
            )

    def _bootstrap_flags(self, goal_reached: np.ndarray) -> np.ndarray:
        """``done`` for the target: HAC stops bootstrapping at a reached goal; the authors' target never stops."""
        return np.zeros_like(goal_reached) if self.paper_compat else goal_reached

    def _add_transitions(
        self, observations: DictObs, actions: np.ndarray, rewards: np.ndarray, next_observations: DictObs, dones: np.ndarray
    ) -> None:
        """Add a batch of higher-level transitions (original observations; SAC normalises them when sampling)."""
        buffer = self.higher.replay_buffer
        assert isinstance(buffer, DictReplayBuffer)
        for row in range(len(actions)):
            buffer.add(
                _rows(observations, slice(row, row + 1)),  # type: ignore[arg-type]
                _rows(next_observations, slice(row, row + 1)),  # type: ignore[arg-type]
                actions[row : row + 1],
                rewards[row : row + 1],
                dones[row : row + 1],
                [{}],
            )

    def _end_open_episodes(self) -> None:
        """An interrupted episode still yields hindsight goals from the options it completed."""
        super()._end_open_episodes()
        for env in self._windows.open_envs():
            self._store_hindsight_goals(env)

    def _has_training_data(self) -> bool:
        return has_finished_episode(self.lower.replay_buffer) and self.higher.replay_buffer.size() > 0  # type: ignore[union-attr]

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_windows", "_episode_counts", "_goal_reached"]
