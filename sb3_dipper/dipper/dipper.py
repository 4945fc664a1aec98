"""DIPPER: direct preference optimization of the higher level of a two-level hierarchy.

Paper: "Direct Preference Optimization for Primitive-Enabled Hierarchical RL: A Bilevel Approach"
(Singh et al., ICLR 2026, https://arxiv.org/abs/2411.00361). No official code is public; the nearest relative is the
authors' PIPER code (https://github.com/Utsavz/piper), from which the preference machinery follows.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import obs_as_tensor

from sb3_dipper.common.deprecation import DeprecatedAttribute, MovedParameter
from sb3_dipper.common.episode_seeds import EPISODE_SEED_KEY, EpisodeSeeds
from sb3_dipper.common.hierarchical import HierarchicalAlgorithm, sibling_path
from sb3_dipper.common.losses import (
    anchor_penalty,
    at_real_steps,
    dipper_loss,
    preference_accuracy,
    preferred_nll,
    tie_share,
    uniform_log_prob,
)
from sb3_dipper.common.low_level import sac_state_value, sac_value_gap
from sb3_dipper.common.option_env import DictObs, low_level_observation
from sb3_dipper.common.planning import GRAPH_REBUILD_TRAJECTORIES as GRAPH_REBUILD_TRAJECTORIES  # public here first
from sb3_dipper.common.planning import PLANNING_MODES as PLANNING_MODES  # public here first
from sb3_dipper.common.planning import SubgoalPlanner
from sb3_dipper.common.preference_pipeline import PreferenceLearner, PreferencePipeline
from sb3_dipper.common.preferences import (
    TrajectoryPairs,
    TrajectoryPairSampler,
    flat_pair_observations,
    policy_preferred_share,
    progress_labels,
    start_gaps,
)
from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.common.validation import (
    InvalidSetting,
    as_bool,
    as_choice,
    as_float,
    as_int,
    as_optional_int,
    check_dict_keys,
    check_keyword_arguments,
    sparse_goal_reached_fn,
)
from sb3_dipper.dipper.policies import DIPPERPolicy, MlpPolicy, MultiInputPolicy
from sb3_dipper.labelling.sources import PreferenceSourceSpec, preference_labeler

SelfDIPPER = TypeVar("SelfDIPPER", bound="DIPPER")

VALUE_REGULARIZERS = ("paper", "score", "reparam")
REFERENCE_POLICIES = ("uniform", "averaged")

#: DIPPER's switches beyond the paper (its ``switch_kwargs``, :ref:`switches`), with their defaults: the paper's DIPPER.
DEFAULT_SWITCH_KWARGS: dict[str, Any] = dict(
    nll_coef=0.0,
    label_smoothing=0.0,
    reference="uniform",
    hindsight_actions=False,
    truncate_at_goal=False,
    goal_subgoal_prob=0.0,
    value_reg="paper",
    value_score_coef=1e-6,
    goal_episode_prob=0.0,
    contrast_env_goals=True,
    anchor_coef=0.0,
    matched_control_prob=0.0,
    twin_episodes=False,
)
# The switches that were DIPPER's parameters before switch_kwargs (still taken as parameters, deprecated).
LEGACY_SWITCHES = (
    "nll_coef",
    "label_smoothing",
    "reference",
    "hindsight_actions",
    "truncate_at_goal",
    "goal_subgoal_prob",
    "value_reg",
    "value_score_coef",
)


def checked_switch_kwargs(switch_kwargs: Mapping[str, Any]) -> dict[str, Any]:
    """``switch_kwargs`` with the defaults (:data:`DEFAULT_SWITCH_KWARGS`) of the keys not given, numbers converted
    (``"1e-2"`` from the zoo becomes ``0.01``) and checked: an unknown key is a ``TypeError`` naming the closest key
    (or all of them), a value out of range an :class:`~sb3_dipper.common.validation.InvalidSetting` naming
    ``switch_kwargs['key']``.

    :param switch_kwargs: DIPPER's ``switch_kwargs``
    """
    check_dict_keys("switch_kwargs", switch_kwargs, DEFAULT_SWITCH_KWARGS)
    settings = {**DEFAULT_SWITCH_KWARGS, **switch_kwargs}
    try:
        settings["nll_coef"] = as_float(
            "switch_kwargs['nll_coef']", settings["nll_coef"], 0.0, reason="it weighs a loss; 0 turns it off"
        )
        settings["label_smoothing"] = as_float(
            "switch_kwargs['label_smoothing']",
            settings["label_smoothing"],
            0.0,
            0.5,
            high_open=True,
            reason="0.5 makes every label a tie",
        )
        settings["reference"] = as_choice("switch_kwargs['reference']", settings["reference"], REFERENCE_POLICIES)
        settings["goal_subgoal_prob"] = as_float("switch_kwargs['goal_subgoal_prob']", settings["goal_subgoal_prob"], 0.0, 1.0)
        settings["goal_episode_prob"] = as_float("switch_kwargs['goal_episode_prob']", settings["goal_episode_prob"], 0.0, 1.0)
        settings["matched_control_prob"] = as_float(
            "switch_kwargs['matched_control_prob']", settings["matched_control_prob"], 0.0, 1.0
        )
        for key in ("hindsight_actions", "truncate_at_goal", "contrast_env_goals", "twin_episodes"):
            settings[key] = as_bool(f"switch_kwargs['{key}']", settings[key])
        if settings["twin_episodes"] and settings["goal_episode_prob"] > 0.0:
            raise InvalidSetting(
                "switch_kwargs['goal_episode_prob']",
                "switch_kwargs['twin_episodes'] chooses the goal-driven episodes itself (the second env of each pair): "
                "leave goal_episode_prob at 0, or twin_episodes at False",
            )
        if settings["matched_control_prob"] > 0.0 and settings["goal_episode_prob"] == 0.0 and not settings["twin_episodes"]:
            raise InvalidSetting(
                "switch_kwargs['matched_control_prob']",
                "switch_kwargs['matched_control_prob'] pairs a policy trajectory with a goal-driven one, which only "
                "goal episodes collect: set switch_kwargs['goal_episode_prob'] above 0 (e.g. 0.5) or twin_episodes "
                "to True, or leave matched_control_prob at 0",
            )
        settings["value_reg"] = as_choice("switch_kwargs['value_reg']", settings["value_reg"], VALUE_REGULARIZERS)
        settings["value_score_coef"] = as_float(
            "switch_kwargs['value_score_coef']", settings["value_score_coef"], 0.0, reason="0 turns the value score off"
        )
        settings["anchor_coef"] = as_float(
            "switch_kwargs['anchor_coef']", settings["anchor_coef"], 0.0, reason="it weighs a loss; 0 turns it off"
        )
    except InvalidSetting as error:
        # The parameter is switch_kwargs: load names it in its advice (load(path, switch_kwargs=...)).
        raise InvalidSetting("switch_kwargs", str(error)) from None
    return settings


class DIPPER(PreferenceLearner, HierarchicalAlgorithm):
    """DIPPER (Singh et al., ICLR 2026): the higher level learns subgoals from preferences by DPO, the lower by SAC+HER.

    The higher level is a squashed-Gaussian policy over subgoals trained only by the DIPPER loss (Eq. 9,
    ``bt_log_sig_2_practical``, of the DIPPER paper) on pairs of higher-level trajectories labelled primitive-in-the-loop
    (Section 4.3). There is no reference policy (a uniform reference: max-entropy token-level DPO). The lower level is
    an SB3 ``SAC`` with ``HerReplayBuffer`` over subgoals (see :class:`HierarchicalAlgorithm` for its parameters).

    :param policy: the higher-level policy (``"MlpPolicy"`` or ``"MultiInputPolicy"``, the same class)
    :param env: a goal env (Dict observations with ``observation``, ``achieved_goal``, ``desired_goal``)
    :param learning_rate: learning rate of the higher-level policy
    :param option_steps: K, primitive steps per subgoal
    :param subgoal_space: subgoal space (default: the env's declared one)
    :param beta: beta, the weight of the policy log-ratios in the DPO logit (Eq. 9)
    :param value_reg_coef: lambda, the weight of the lower-value regulariser (Eq. 9; 0: DIPPER-No-V); how it enters is
        ``switch_kwargs["value_reg"]``
    :param value_steps: m, lower critic gradient steps between ``V^L`` and ``V^L_m``
    :param n_preference_pairs: the label budget: pairs labelled over the whole run, spread over training
    :param pairs_per_batch: preference pairs per higher-level gradient step
    :param hindsight_goal_prob: probability that both trajectories of a pair share a goal achieved by one of them
    :param segment_options: options per trajectory of a preference pair: each pair compares segments of this many
        consecutive options cut from two stored trajectories, so that a label credits the subgoals that made the
        difference (beyond the paper; ``None``: whole trajectories, the paper's). It sets the stored pairs' shape, so it
        is fixed when the model is built
    :param random_subgoal_prob: probability of a uniformly random subgoal during training (exploration)
    :param high_gradient_steps: higher-level gradient steps per option
    :param switch_kwargs: the switches beyond the paper (:ref:`switches`; default: none on, the paper's DIPPER), a dict
        with the keys ``nll_coef`` (weight of the preferred trajectory's negative log-likelihood added to the loss,
        RPO-style; 0: off), ``label_smoothing`` (epsilon of conservative DPO: each strict label counts as flipped with
        probability epsilon; 0: off), ``reference`` (the DPO logit's reference policy: ``"uniform"``, the paper's, or
        ``"averaged"``, the Polyak average of the trained actor, which needs ``policy_kwargs`` ``acting_tau`` below 1),
        ``hindsight_actions`` (train on the subgoal each option reached instead of the one proposed),
        ``truncate_at_goal`` (end each pair when the first of its trajectories reaches the goal), ``goal_subgoal_prob``
        (probability that a training subgoal is the env's goal itself; 0: off), ``value_reg`` (how lambda enters:
        ``"paper"``, Eq. 9's ``-lambda * sum_t (V^L - V^L_m)`` in the DPO logit; ``"score"``, the PIPER code's
        ``value_score_coef * sum_t V^L(s_t, g_t)`` added to the preference score at labelling; ``"reparam"``,
        ``-lambda * E_{u ~ pi^H}[V^L(s, g(u))]`` added to the loss), ``value_score_coef`` (the weight of that sum
        with ``"score"``, in place of lambda; default 1e-6, the PIPER code's ``q_reg``, so that the value only breaks
        ties), ``goal_episode_prob`` (probability that an env's training episode is driven by the goal as every
        subgoal, the control, so that pairs compare whole control trajectories with the policy's; 0: off),
        ``contrast_env_goals`` (whether a pair of a goal-driven trajectory and another keeps the env's goals instead of
        a hindsight goal; default True), ``matched_control_prob`` (probability that a pair is a trajectory of the
        policy's and the goal-driven trajectory whose start, its achieved goal and goal at the first option, is
        nearest, so that a label compares the policy's subgoals with the control's from about the same start; needs
        ``goal_episode_prob`` above 0 or ``twin_episodes``; 0: off), ``twin_episodes`` (the envs run in pairs that
        play the same episodes, each wrapped in :class:`~sb3_dipper.common.episode_seeds.EpisodeSeeds`, the second of
        each pair driven by the goal as every subgoal, in place of ``goal_episode_prob``; a matched pair is then a
        policy trajectory and its twin, same layout, start and goal; default False) and ``anchor_coef`` (weight of a
        goal-anchored policy's squared offset from the goal's action added to the loss, a leash that keeps its
        subgoals at the goal where the preferences do not pull them off; needs ``policy_kwargs``
        ``goal_anchored=True``; 0: off), for example
        ``dict(nll_coef=1.0, hindsight_actions=True, truncate_at_goal=True)``
        (:data:`DEFAULT_SWITCH_KWARGS`); ``model.switch_kwargs`` holds them all, and a key changed there acts from the
        next :meth:`learn`. Each key but the last five is also taken as a parameter of its own, deprecated
    :param planner_kwargs: planning over achieved states, the keyword arguments of the planner,
        :class:`~sb3_dipper.common.planning.SubgoalPlanner` (``model.planner``; default: no planning, the paper):
        ``mode`` ``"off"``, ``"subgoal"`` (where its graph knows a path to the goal, propose the waypoint on it;
        elsewhere the policy proposes) or ``"waypoint"`` (the policy always proposes, conditioned on the waypoint
        instead of the goal); ``lookahead`` (options along the shortest known path to the waypoint), ``resolution``
        (voxel size of the graph; default: the subgoal threshold), ``value_threshold`` (keep a graph edge only if the
        lower level's value ``min_i Q_i(s, g, mu(s, g))`` of reaching its target voxel from the start of some option
        that took it is at least this) and ``in_predict`` (``False``, only with ``"subgoal"``: the planner steers the
        training proposals, and the preference-trained policy proposes every subgoal in :meth:`predict`; such a model
        can be exported, :meth:`export_policy`). For example ``dict(mode="subgoal", lookahead=2)``. The planner says
        per row whether it planned (:class:`~sb3_dipper.common.planning.Plan`), and only there does its waypoint
        replace the policy's proposal. The graph knows places only: where obstacles move between episodes (random
        maze layouts) its paths may cross the current episode's walls. With ``"subgoal"`` the share of training
        subgoals that were the planner's (random subgoals excluded) is logged as ``rollout/planned_share``, and
        :attr:`last_planned` tells which envs' last subgoal was the planner's. Its keys were parameters of their own
        before (``planning``, ``plan_in_predict``, ``planning_lookahead``, ``planning_resolution``,
        ``planning_value_threshold``), still taken, deprecated
    :param trajectory_buffer_size: number of higher-level trajectories kept for pair sampling
    :param preference_source: labels pairs (default: primitive-in-the-loop labels from the env's sparse reward); also
        ``"noisy:P"``, ``"people:DIRECTORY"``, ``"mixed:DIRECTORY:FRACTION"`` or a dict (see
        :func:`~sb3_dipper.labelling.sources.preference_source_from`)
    :param buffer_size: lower-level replay buffer size
    :param learning_starts: primitive steps of random subgoals and lower actions before learning
    :param batch_size: lower-level minibatch size
    :param tau: lower-level target smoothing coefficient
    :param gamma: lower-level discount factor
    :param train_freq: lower-level training frequency (primitive vec-env steps)
    :param gradient_steps: lower-level gradient steps per training round
    :param ent_coef: lower-level entropy coefficient
    :param replay_buffer_kwargs: lower ``HerReplayBuffer`` kwargs
    :param low_learning_rate: lower-level learning rate
    :param low_policy_kwargs: lower SAC ``policy_kwargs``
    :param low_level_kwargs: other lower ``SAC`` kwargs (not those set by a parameter here, such as ``buffer_size``)
    :param demo_kwargs: the lower level's behaviour cloning of demonstrations, a dict with the keys ``demo_path``
        (default ``None``: none), ``n_demos``, ``demo_share``, ``bc_coef``, ``rl_coef``, ``q_filter`` and
        ``normalize_from_demos`` (see :class:`~sb3_dipper.common.hierarchical.HierarchicalAlgorithm`), for example
        ``dict(demo_path="auto", bc_coef=0.02)``; each key is also taken as a parameter of its own, deprecated
    :param greedy_episode_prob: probability that an env's training episode is collected with the lower level acting
        greedily (its deterministic action) while the higher level explores (beyond the paper; 0: off)
    :param max_episode_steps: base episode length (default: the env's time limit)
    :param policy_kwargs: higher-level policy kwargs (``net_arch``, ``acting_tau``, ...)
    :param stats_window_size: window of rollout statistics
    :param tensorboard_log: tensorboard folder
    :param verbose: verbosity
    :param seed: random seed
    :param device: torch device
    :param _init_setup_model: build the networks now
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"MlpPolicy": MlpPolicy, "MultiInputPolicy": MultiInputPolicy}
    policy: DIPPERPolicy
    # Saved with the model (load() restores it before _setup_model), with its graph, so that a loaded model plans as it did.
    planner: SubgoalPlanner
    # The planner's settings were parameters of their own; None stood for the planner's default.
    # The switches beyond the paper were parameters of their own too.
    deprecated_parameters: ClassVar[Mapping[str, MovedParameter]] = {
        **HierarchicalAlgorithm.deprecated_parameters,
        **{
            name: MovedParameter("planner_kwargs", key, holder="planner", none_is_unset=True)
            for name, key in (
                ("planning", "mode"),
                ("plan_in_predict", "in_predict"),
                ("planning_lookahead", "lookahead"),
                ("planning_resolution", "resolution"),
                ("planning_value_threshold", "value_threshold"),
            )
        },
        **{name: MovedParameter("switch_kwargs", name) for name in LEGACY_SWITCHES},
    }
    # The switches checked and completed with their defaults (a model saved before a switch existed loads with it).
    switch_kwargs: dict[str, Any]
    subgoal_graph = DeprecatedAttribute("planner", "graph")
    # The lower update count when the lower critic was last copied into the snapshot V^L_m (saved with the model, as
    # the snapshot is), so that a loaded model refreshes the snapshot on the schedule it had.
    _value_snapshot_updates: int = 0

    def __init__(
        self,
        policy: str | type[DIPPERPolicy],
        env: GymEnv | str | None,
        learning_rate: float | Schedule = 1e-3,
        option_steps: int = 15,
        subgoal_space: SubgoalSpace | None = None,
        beta: float = 0.1,
        value_reg_coef: float = 0.1,
        value_steps: int = 15,
        n_preference_pairs: int = 10_000,
        pairs_per_batch: int = 64,
        hindsight_goal_prob: float = 0.8,
        segment_options: int | None = None,
        random_subgoal_prob: float = 0.2,
        high_gradient_steps: int = 1,
        switch_kwargs: dict[str, Any] | None = None,
        planner_kwargs: dict[str, Any] | None = None,
        trajectory_buffer_size: int = 5000,
        preference_source: PreferenceSourceSpec = None,
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
        self.beta = beta
        self.value_reg_coef = value_reg_coef
        self.value_steps = value_steps
        self.n_preference_pairs = n_preference_pairs
        self.pairs_per_batch = pairs_per_batch
        self.hindsight_goal_prob = hindsight_goal_prob
        self.segment_options = segment_options
        self.high_gradient_steps = high_gradient_steps
        self.switch_kwargs = dict(switch_kwargs or {})
        self.planner_kwargs = dict(planner_kwargs or {})
        self.trajectory_buffer_size = trajectory_buffer_size
        self.preference_source = preference_source
        if _init_setup_model:
            self._setup_model()

    def _check_settings(self) -> None:
        super()._check_settings()
        self.hindsight_goal_prob = as_float("hindsight_goal_prob", self.hindsight_goal_prob, 0.0, 1.0)
        self.beta = as_float("beta", self.beta, 0.0, low_open=True, reason="beta <= 0 trains toward the rejected trajectories")
        self.value_reg_coef = as_float("value_reg_coef", self.value_reg_coef, 0.0, reason="0 turns the value term off")
        self.value_steps = as_int("value_steps", self.value_steps, 0)
        self.n_preference_pairs = as_int("n_preference_pairs", self.n_preference_pairs, 1)
        self.pairs_per_batch = as_int("pairs_per_batch", self.pairs_per_batch, 1)
        self.high_gradient_steps = as_int("high_gradient_steps", self.high_gradient_steps, 0)
        self.segment_options = as_optional_int(
            "segment_options", self.segment_options, 1, "None compares whole trajectories, the paper's pairs"
        )
        self.switch_kwargs = checked_switch_kwargs(self.switch_kwargs)
        self.trajectory_buffer_size = as_int(
            "trajectory_buffer_size", self.trajectory_buffer_size, 2, "preference pairs need two stored trajectories"
        )
        self._check_planner()

    def _setup_high_level(self) -> None:
        assert self.subgoal_space is not None
        self.policy = self.policy_class(  # type: ignore[assignment]
            self.observation_space, self.subgoal_space.unit_box, self.lr_schedule, **self.policy_kwargs
        ).to(self.device)
        self._goal_reached, labeler = None, None
        if self.env is not None:  # a model without an env labels nothing until it gets one
            self._goal_reached = sparse_goal_reached_fn(self.env, type(self).__name__)
            labeler = preference_labeler(
                self.preference_source,
                self.env,
                self.subgoal_space,
                self.seed,
                self._pair_value_score,
                self._goal_reached,
                label_budget=self.n_preference_pairs,
            )
        if self.segment_options is not None and self.segment_options > self.high_steps:
            raise InvalidSetting(
                "segment_options",
                f"segment_options={self.segment_options} is longer than a higher-level trajectory ({self.high_steps} "
                f"options): use at most {self.high_steps}, or None for whole trajectories",
            )
        self._pair_sampler = TrajectoryPairSampler(
            self.hindsight_goal_prob, self.subgoal_space, segment_options=self.segment_options
        )
        self.preference_pipeline = PreferencePipeline(
            self._higher_level_trajectory_buffer(self.trajectory_buffer_size),
            self.n_preference_pairs,
            self._pair_sampler,
            labeler,
        )
        self.planner.setup(self.subgoal_space)
        self._reference_log_prob = uniform_log_prob(self.subgoal_space.dim)
        self._apply_switches()
        # A loaded model puts the saved snapshot back (set_parameters) and keeps its _value_snapshot_updates.
        self._value_snapshot = copy.deepcopy(self.lower.critic).requires_grad_(False)
        # Which envs' last higher-level decision was the planner's waypoint instead of the policy's proposal.
        self.last_planned = np.zeros(self.n_envs, dtype=bool)
        # Which envs' training episode the goal drives (goal_episode_prob); None: drawn at the next decision.
        self.goal_episodes: np.ndarray | None = None
        self._refresh_goal_anchor()

    def _apply_switches(self) -> None:
        """Check ``switch_kwargs`` and set the part of the model built from them (the pair sampler's truncation at the
        goal and its contrast pairs' goals), so that a switch changed in ``model.switch_kwargs`` after the model was
        built acts from the next :meth:`learn`; training reads the others from ``switch_kwargs`` where it uses them."""
        self.switch_kwargs = checked_switch_kwargs(self.switch_kwargs)
        self._pair_sampler.goal_reached = self._goal_reached if self.switch_kwargs["truncate_at_goal"] else None
        self._pair_sampler.contrast_env_goals = self.switch_kwargs["contrast_env_goals"]
        self._pair_sampler.matched_control_prob = self.switch_kwargs["matched_control_prob"]
        self._pair_sampler.match_twins = self.switch_kwargs["twin_episodes"]
        if self.switch_kwargs["anchor_coef"] > 0.0 and not self.policy.goal_anchored:
            raise ValueError(
                "switch_kwargs['anchor_coef'] pulls a goal-anchored policy's subgoals toward the goal: set policy_kwargs "
                "goal_anchored=True, or leave anchor_coef at 0"
            )
        if self.switch_kwargs["reference"] == "averaged" and self.policy.averaged_actor is None:
            raise ValueError(
                "switch_kwargs['reference']='averaged' needs an averaged actor: set policy_kwargs acting_tau below 1 "
                "(e.g. 0.05)"
            )

    def _refresh_low_normalizer(self) -> None:
        super()._refresh_low_normalizer()
        if getattr(self, "policy", None) is not None:  # the setup refreshes the statistics before it builds the policy
            self._refresh_goal_anchor()

    def _refresh_goal_anchor(self) -> None:
        """Point a goal-anchored policy (``policy_kwargs`` ``goal_anchored``) at the goal under the current statistics."""
        if not self.policy.goal_anchored:
            return
        assert self.subgoal_space is not None
        goal_dim = self.observation_space["desired_goal"].shape[0]  # type: ignore[index]
        mean, std = np.zeros(goal_dim), np.ones(goal_dim)
        if self.low_normalizer is not None:
            mean, std = self.low_normalizer.goal_mean_and_std("desired_goal", goal_dim)
        self.policy.set_goal_anchor(*self.subgoal_space.goal_unit_map(mean, std))

    def _check_planner(self) -> None:
        """Build :attr:`planner` from ``planner_kwargs``, checked as the constructor checks them. A loaded model's planner
        keeps its graph, and ``planner_kwargs`` given to ``load`` replace its keys. A model saved before
        ``planner_kwargs`` has its planning settings in ``planner_kwargs`` by now (``_check_settings``), and its graph
        as an attribute of its own."""
        legacy_names = ("subgoal_graph", "_trajectories_since_graph")
        legacy = {name: self.__dict__.pop(name) for name in legacy_names if name in self.__dict__}
        loaded: SubgoalPlanner | None = self.__dict__.get("planner")
        settings = {**(loaded.settings if loaded is not None else {}), **(self.planner_kwargs or {})}
        check_keyword_arguments(SubgoalPlanner, settings, source="planner_kwargs")
        try:
            planner = SubgoalPlanner(**settings)
        except ValueError as error:
            raise InvalidSetting("planner_kwargs", str(error)) from error
        planner.graph = legacy.get("subgoal_graph", loaded.graph if loaded is not None else None)
        if loaded is not None:
            self.planner_kwargs = settings
        self.planner = planner

    def _predict_plans(self) -> bool:
        return self.planner.plans_in_predict

    def _option_metric_keys(self) -> tuple[str, ...]:
        planned = ("planned_share",) if self.planner.proposes_subgoals else ()
        goal_driven: tuple[str, ...] = ()
        if self._collects_goal_episodes:
            goal_driven = ("goal_episode_share", "goal_episode_success", "policy_episode_success")
        return (*super()._option_metric_keys(), *planned, *goal_driven)

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> tuple[int, BaseCallback]:
        self._apply_switches()
        if self.switch_kwargs["twin_episodes"]:
            self._seed_twin_episodes(resetting=reset_num_timesteps or self._last_obs is None)
        return super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)

    @property
    def _collects_goal_episodes(self) -> bool:
        """Whether some training episodes are driven by the goal as every subgoal (``goal_episode_prob`` or
        ``twin_episodes``)."""
        return self.switch_kwargs["goal_episode_prob"] > 0.0 or self.switch_kwargs["twin_episodes"]

    def _seed_twin_episodes(self, resetting: bool) -> None:
        """``twin_episodes``: give each pair of envs (0 and 1, 2 and 3, ...) one seed stream for its episodes, just
        before the env is reset (``resetting``), so that the two play the same episodes; a ``learn`` that goes on
        without a reset needs the streams already set."""
        assert self.env is not None
        if self.n_envs % 2 != 0:
            raise InvalidSetting(
                "switch_kwargs['twin_episodes']",
                f"switch_kwargs['twin_episodes'] runs the envs in pairs, but the env has {self.n_envs}: use an even "
                "n_envs (e.g. 2), or twin_episodes=False",
            )
        if not all(self.env.env_is_wrapped(EpisodeSeeds)):
            raise InvalidSetting(
                "switch_kwargs['twin_episodes']",
                "switch_kwargs['twin_episodes'] seeds the envs' episodes, which needs every env wrapped in "
                "sb3_dipper.common.episode_seeds.EpisodeSeeds (make_vec_env(..., wrapper_class=EpisodeSeeds), or "
                "env_wrapper: sb3_dipper.common.episode_seeds.EpisodeSeeds in the zoo's hyperparameters)",
            )
        if not resetting:
            if not all(self.env.get_attr("episodes_seeded")):
                raise InvalidSetting(
                    "switch_kwargs['twin_episodes']",
                    "switch_kwargs['twin_episodes'] needs the envs' episodes seeded in pairs, but this learn goes on "
                    "without a reset on an env whose episodes are not (set_env(env, force_reset=False)?): call "
                    "set_env(env) or learn(..., reset_num_timesteps=True)",
                )
            return
        for pair in range(self.n_envs // 2):
            self.env.env_method("seed_episodes", int(self._rng.integers(2**62)), indices=[2 * pair, 2 * pair + 1])

    def learn(
        self: SelfDIPPER,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "DIPPER",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfDIPPER:
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    # ---------------------------------------------------------------------------------------------------- acting

    def _high_level_actions(self, observation: DictObs, deterministic: bool) -> np.ndarray:
        return self._proposals(observation, deterministic, training=False)

    def _collecting_high_level_actions(self, observation: DictObs) -> np.ndarray:
        return self._proposals(observation, deterministic=False, training=True)

    def _proposals(self, observation: DictObs, deterministic: bool, training: bool) -> np.ndarray:
        """The policy's subgoals, steered by the planner (:meth:`~sb3_dipper.common.planning.SubgoalPlanner.propose`);
        :attr:`last_planned` records which rows' subgoal is the planner's waypoint."""
        action_dim = self.policy.action_space.shape[0]  # type: ignore[index]

        def policy_proposals(policy_input: DictObs) -> np.ndarray:
            actions, _ = self.policy.predict(policy_input, deterministic=deterministic)  # type: ignore[arg-type]
            return np.asarray(actions, dtype=np.float32).reshape(-1, action_dim)

        actions, self.last_planned = self.planner.propose(observation, policy_proposals, self.low_normalizer, training)
        return actions

    def _training_high_level_actions(self, observation: DictObs) -> np.ndarray:
        self.last_planned = np.zeros(self.n_envs, dtype=bool)  # the warm-up's uniform subgoals are nobody's plan
        actions = super()._training_high_level_actions(observation)
        self.last_planned &= ~self.last_random_subgoals  # a random subgoal replaced the planner's waypoint
        goal_subgoal_prob = self.switch_kwargs["goal_subgoal_prob"]
        if goal_subgoal_prob > 0.0 and self.num_timesteps >= self.learning_starts:
            goal_rows = (self._rng.random(self.n_envs) < goal_subgoal_prob) & ~self.last_random_subgoals
            actions[goal_rows] = self._subgoal_actions(observation["desired_goal"])[goal_rows]
            self.last_planned &= ~goal_rows
        if self._collects_goal_episodes and self.num_timesteps >= self.learning_starts:
            actions = self._drive_goal_episodes(observation, actions)
        if self.planner.proposes_subgoals and self.num_timesteps >= self.learning_starts:
            self._option_metrics["planned_share"].extend(self.last_planned.astype(np.float64))
        return actions

    def _drive_goal_episodes(self, observation: DictObs, actions: np.ndarray) -> np.ndarray:
        """``goal_episode_prob`` or ``twin_episodes``: the goal is every subgoal of the envs whose episode
        :attr:`goal_episodes` marks (the control, not explored and not planned), so that stored trajectories include
        whole control episodes."""
        if self.goal_episodes is None:
            self._draw_goal_episodes(np.ones(self.n_envs, dtype=bool))
        assert self.goal_episodes is not None
        goal_rows = self.goal_episodes
        actions[goal_rows] = self._subgoal_actions(observation["desired_goal"])[goal_rows]
        self.last_planned &= ~goal_rows
        self.last_random_subgoals &= ~goal_rows
        self._option_metrics["goal_episode_share"].extend(goal_rows.astype(np.float64))
        return actions

    def _record_success_by_driver(self, dones: np.ndarray, infos: list[dict[str, Any]]) -> None:
        """The success of each finished training episode, as ``rollout/goal_episode_success`` where the goal drove it and
        ``rollout/policy_episode_success`` where the higher level did: who succeeds in training, on the same tasks."""
        assert self.goal_episodes is not None
        for env_idx in np.flatnonzero(dones):
            success = infos[env_idx].get("is_success")
            if success is not None:
                key = "goal_episode_success" if self.goal_episodes[env_idx] else "policy_episode_success"
                self._option_metrics[key].append(float(success))

    def _draw_goal_episodes(self, starting: np.ndarray) -> None:
        """Whether the envs of the mask ``starting`` have their next episode driven by the goal: drawn with
        ``goal_episode_prob``, or with ``twin_episodes`` the second env of each pair."""
        if self.switch_kwargs["twin_episodes"]:
            self.goal_episodes = np.arange(self.n_envs) % 2 == 1
            return
        self.goal_episodes = self._drawn_episode_flags(self.goal_episodes, starting, self.switch_kwargs["goal_episode_prob"])

    def _lower_level_value(self, start_observations: DictObs, targets: np.ndarray) -> np.ndarray:
        """The lower level's value ``min_i Q_i(s, g, mu(s, g))`` of reaching each target (world units) from each start
        state, which the planner's ``value_threshold`` compares."""
        assert self.subgoal_space is not None
        values = []
        with th.no_grad():
            for chunk in range(0, targets.shape[0], 4096):
                rows = slice(chunk, chunk + 4096)
                batch = {key: value[rows] for key, value in start_observations.items()}
                low_obs = self.low_level.tensor_obs(low_level_observation(batch, targets[rows], self.subgoal_space))
                actions = self.lower.actor(low_obs, deterministic=True)
                values.append(th.cat(self.lower.critic(low_obs, actions), dim=1).min(dim=1).values.cpu().numpy())
        return np.concatenate(values)

    def _store_option(
        self,
        start_obs: DictObs,
        high_actions: np.ndarray,
        new_obs: DictObs,
        rewards: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        assert self.option_env is not None and self.option_env.reached_obs is not None
        reached = self.option_env.reached_obs["achieved_goal"]
        seeds = np.array([info.get(EPISODE_SEED_KEY, -1) for info in infos], dtype=np.int64)
        self.trajectory_buffer.add(
            start_obs, high_actions, reached, dones, goal_driven=self.goal_episodes, episode_seeds=seeds
        )
        self.planner.trajectories_finished(int(np.sum(dones)), self.trajectory_buffer, self._lower_level_value)
        if self.goal_episodes is not None:
            self._record_success_by_driver(dones, infos)
            self._draw_goal_episodes(dones)

    def _end_open_episodes(self) -> None:
        super()._end_open_episodes()
        self.trajectory_buffer.discard_open()
        self.goal_episodes = None  # the envs start new episodes: each is drawn at its first decision

    # ---------------------------------------------------------------------------------------------------- training

    def train(self) -> None:
        """Lower SAC updates (which also move V^L toward V^L_m), new labels, then the higher-level DIPPER updates."""
        self._train_low_level()
        new_pairs = self.preference_pipeline.label_new_pairs(self.num_timesteps, self._total_timesteps, self._rng)
        if new_pairs is not None:
            self._record_label_diagnostics(new_pairs)
        if len(self.preferences) == 0:
            return
        self._train_high_level()

    def _train_high_level(self) -> None:
        """``high_gradient_steps`` DIPPER updates of the higher policy on sampled labelled pairs."""
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.actor.optimizer)
        terms: dict[str, list[float]] = {}
        for _ in range(self.high_gradient_steps):
            pairs = self.preferences.sample(self.pairs_per_batch, self._rng)
            loss, logged = self.high_level_loss(pairs)
            self.policy.actor.optimizer.zero_grad()
            loss.backward()
            self.policy.actor.optimizer.step()
            self.policy.update_averaged_actor()
            for key, value in logged.items():
                terms.setdefault(key, []).append(value)
        self._refresh_value_snapshot()
        self._n_updates += self.high_gradient_steps
        self.logger.record("train/high_n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/high_preference_pairs", len(self.preferences))
        for key, values in terms.items():
            self.logger.record(f"train/high_{key}", float(np.mean(values)))

    def high_level_loss(self, pairs: TrajectoryPairs) -> tuple[th.Tensor, dict[str, float]]:
        """The higher policy's loss on labelled ``pairs`` (one update's batch) and its terms to log (``dpo_loss``,
        ``tie_share``, and where they apply ``nll``, ``anchor_offset``, ``pref_accuracy``, ``value_gap``)."""
        switches = self.switch_kwargs
        value_term = switches["value_reg"] if self.value_reg_coef != 0.0 else None
        observations, actions, mask, labels = self._pair_tensors(pairs)

        # Eq. 9: log pi^H of every stored higher-level action, minus lambda * (V^L - V^L_m) per step. Every term is
        # masked, so the networks see only the real steps (on pick-and-place about a fifth of the padded (2, B, T) batch).
        log_probs = at_real_steps(self.policy.log_prob(observations, actions), mask)
        gaps = self._value_gaps(pairs, mask) if value_term == "paper" else None
        reference = self._reference_log_probs(observations, actions, mask)
        dpo, logits = dipper_loss(
            log_probs, mask, labels, self.beta, reference, gaps, self.value_reg_coef, switches["label_smoothing"]
        )
        loss = dpo
        logged = {"dpo_loss": dpo.item(), "tie_share": tie_share(labels)}

        # Optional: the preferred side's likelihood (RPO-style), against likelihood displacement.
        if switches["nll_coef"] > 0.0:
            nll = preferred_nll(log_probs, mask, labels)
            loss = loss + switches["nll_coef"] * nll
            logged["nll"] = nll.item()

        # Optional: a leash that keeps a goal-anchored policy at the goal where the preferences do not pull it off.
        if switches["anchor_coef"] > 0.0:
            leash = anchor_penalty(self.policy.actor.offset_from_the_anchor(observations))
            loss = loss + switches["anchor_coef"] * leash
            logged["anchor_offset"] = leash.item()

        # Optional: push proposals toward subgoals the lower level values (value_reg="reparam").
        if value_term == "reparam":
            loss = loss - self.value_reg_coef * self._reparameterised_low_value(pairs, observations).mean()

        accuracy = preference_accuracy(logits.detach(), labels)
        if accuracy is not None:
            logged["pref_accuracy"] = accuracy
        if gaps is not None:
            logged["value_gap"] = (gaps * mask).sum().item() / max(mask.sum().item(), 1.0)
        return loss, logged

    def _record_label_diagnostics(self, pairs: TrajectoryPairs) -> None:
        """What the new labels carry, and how the policy does on pairs it has not trained on yet (logged as means over
        the options between two log dumps): the share of ties, how far apart the two trajectories of a pair started
        (:func:`~sb3_dipper.common.preferences.start_gaps`), the agreement with an oracle of the true progress
        (:func:`~sb3_dipper.common.preferences.progress_labels`), how often a pair of the goal-driven control and the
        policy prefers the policy's (:func:`~sb3_dipper.common.preferences.policy_preferred_share`), the DPO accuracy,
        and the mean per-step log-likelihood of the preferred and the rejected trajectories (both falling is likelihood
        displacement)."""
        labelled = pairs.select(np.flatnonzero(~np.isnan(pairs.labels)))
        if len(labelled) == 0:
            return
        self.logger.record_mean("train/high_new_tie_share", float(np.mean(labelled.labels == 0.5)))
        self.logger.record_mean("train/high_new_start_gap", float(np.mean(start_gaps(labelled))))
        agreement = float(np.mean(labelled.labels == progress_labels(labelled)))
        self.logger.record_mean("train/high_label_progress_agreement", agreement)
        policy_preferred = policy_preferred_share(labelled)
        if policy_preferred is not None:
            self.logger.record_mean("train/high_new_policy_preferred", policy_preferred)
        with th.no_grad():
            observations, actions, mask, labels = self._pair_tensors(labelled)
            log_probs = at_real_steps(self.policy.log_prob(observations, actions), mask)
            reference = self._reference_log_probs(observations, actions, mask)
            _, logits = dipper_loss(log_probs, mask, labels, self.beta, reference)
            accuracy = preference_accuracy(logits, labels)
            if accuracy is not None:
                self.logger.record_mean("train/high_new_pair_accuracy", accuracy)
                self.logger.record_mean("train/high_new_logp_preferred", -preferred_nll(log_probs, mask, labels).item())
                self.logger.record_mean("train/high_new_logp_rejected", -preferred_nll(log_probs, mask, 1 - labels).item())

    def _reference_log_probs(
        self, observations: dict[str, th.Tensor], actions: th.Tensor, mask: th.Tensor
    ) -> float | th.Tensor:
        """The reference policy's per-step log-density: the uniform constant, or the averaged actor's ``(2, B, T)``."""
        if self.switch_kwargs["reference"] == "uniform":
            return self._reference_log_prob
        with th.no_grad():
            return at_real_steps(self.policy.averaged_log_prob(observations, actions), mask)

    def _pair_actions(self, pairs: TrajectoryPairs) -> np.ndarray:
        return pairs.reached_actions if self.switch_kwargs["hindsight_actions"] else pairs.actions

    def _pair_tensors(self, pairs: TrajectoryPairs) -> tuple[dict[str, th.Tensor], th.Tensor, th.Tensor, th.Tensor]:
        """(Normalised) observations and actions of the real steps of both trajectories, one row per step in the order
        of ``pairs.mask``'s true entries; the mask ``(2, B, T)`` and labels as tensors."""
        real_steps = pairs.mask.reshape(-1)
        flat_obs = {key: value[real_steps] for key, value in flat_pair_observations(pairs).items()}
        if self._vec_normalize_env is not None:
            flat_obs = self._vec_normalize_env.normalize_obs(flat_obs)  # type: ignore[assignment]
        observations = obs_as_tensor(flat_obs, self.device)  # type: ignore[arg-type]
        pair_actions = self._pair_actions(pairs)
        actions = th.as_tensor(pair_actions.reshape(-1, pair_actions.shape[-1])[real_steps], device=self.device)
        mask = th.as_tensor(pairs.mask, device=self.device)
        labels = th.as_tensor(pairs.labels, device=self.device)
        return observations, actions, mask, labels  # type: ignore[return-value]

    def _pair_low_obs(self, pairs: TrajectoryPairs, actions: np.ndarray, real_only: bool = False) -> dict[str, th.Tensor]:
        """Lower-level observations (s_t, g_t) of every step of both trajectories, g_t the subgoal of ``actions``.

        :param real_only: only the real steps (``pairs.mask``), in the order of the mask's true entries
        """
        assert self.subgoal_space is not None
        flat_obs = flat_pair_observations(pairs)
        actions = actions.reshape(-1, actions.shape[-1])
        if real_only:
            real_steps = pairs.mask.reshape(-1)
            flat_obs, actions = {key: value[real_steps] for key, value in flat_obs.items()}, actions[real_steps]
        subgoals = self.subgoal_space.to_world(actions)
        return self.low_level.tensor_obs(low_level_observation(flat_obs, subgoals, self.subgoal_space))

    def _value_gaps(self, pairs: TrajectoryPairs, mask: th.Tensor) -> th.Tensor:
        """Per-step ``V^L(s_t, g_t) - V^L_m(s_t, g_t)`` of both trajectories, shape ``(2, B, T)`` (0 at the padding, which
        every loss term masks out, so the lower networks evaluate only the real steps), no gradient."""
        with th.no_grad():
            low_obs = self._pair_low_obs(pairs, self._pair_actions(pairs), real_only=True)
            # The sample's noise is drawn for every step, padding included, as sampling every step would draw it: the
            # random stream, and so a seeded run, stays the one of evaluating the padded batch.
            noise = th.empty((mask.numel(), self.lower.actor.action_dist.action_dim), device=self.device).normal_()
            return at_real_steps(sac_value_gap(self.lower, self._value_snapshot, low_obs, noise[mask.reshape(-1)]), mask)

    def _refresh_value_snapshot(self) -> None:
        """Once the lower critic is ``value_steps`` updates past the snapshot, the current critic becomes the snapshot."""
        if self.lower._n_updates - self._value_snapshot_updates >= self.value_steps:
            self._value_snapshot.load_state_dict(self.lower.critic.state_dict())
            self._value_snapshot_updates = self.lower._n_updates

    def _pair_value_score(self, pairs: TrajectoryPairs) -> np.ndarray:
        """What the labeller adds to each trajectory's primitive-in-the-loop score, shape ``(2, B)``: with
        ``switch_kwargs["value_reg"] == "score"`` PIPER's label-time term ``value_score_coef * sum_t V^L(s_t, g_t)``,
        else 0 (read at labelling, so that the switch acts whenever it is set)."""
        if self.switch_kwargs["value_reg"] != "score":
            return np.zeros(pairs.mask.shape[:2])
        with th.no_grad():
            values = sac_state_value(self.lower, self._pair_low_obs(pairs, pairs.actions)).cpu().numpy()
        return self.switch_kwargs["value_score_coef"] * (values.reshape(pairs.mask.shape) * pairs.mask).sum(axis=-1)

    def _reparameterised_low_value(self, pairs: TrajectoryPairs, observations: dict[str, th.Tensor]) -> th.Tensor:
        """``V^L(s, g(u))`` for ``u ~ pi^H(.|s, g*)`` (reparameterised, so it has a gradient), at the pairs' real steps.

        :param observations: the higher-level observations of the real steps (from :meth:`_pair_tensors`)
        """
        assert self.subgoal_space is not None
        actions, _ = self.policy.sample_with_log_prob(observations)
        low_obs = self._pair_low_obs(pairs, pairs.actions, real_only=True)
        low_obs["desired_goal"] = self.low_level.normalize_subgoal_tensor(self.subgoal_space.to_world_tensor(actions))
        self.lower.policy.requires_grad_(False)
        values = sac_state_value(self.lower, low_obs)
        self.lower.policy.requires_grad_(True)
        return values

    # ---------------------------------------------------------------------------------------------------- saving

    def save(self, path: Any, exclude: Any = None, include: Any = None) -> None:
        """SB3's ``save``. The saved ``planner_kwargs`` are the planner's settings as it acts (changed through
        ``model.planner`` or not), so that ``load`` restores that planner and a key given to ``load`` replaces just its own.
        """
        self.planner_kwargs = {**self.planner_kwargs, **self.planner.settings}
        super().save(path, exclude, include)

    def _excluded_save_params(self) -> list[str]:
        # The pair sampler and the goal test are rebuilt with the model (the goal test holds the env).
        return [*super()._excluded_save_params(), "last_planned", "goal_episodes", "_pair_sampler", "_goal_reached"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        return ["policy", "policy.actor.optimizer", "_value_snapshot", *state_dicts], variables

    def set_parameters(
        self, load_path_or_dict: str | dict[str, Any], exact_match: bool = True, device: th.device | str = "auto"
    ) -> None:
        """SB3's ``set_parameters``. A file saved before the value snapshot was saved with the model starts the
        snapshot from its lower critic, as a snapshot refresh would."""
        params = load_path_or_dict
        if isinstance(params, dict) and "_value_snapshot" not in params and "lower.policy" in params:
            lower_policy = params["lower.policy"].items()
            critic = {name.removeprefix("critic."): value for name, value in lower_policy if name.startswith("critic.")}
            params = {**params, "_value_snapshot": critic}
            self._value_snapshot_updates = self.lower._n_updates
        super().set_parameters(params, exact_match, device)  # type: ignore[arg-type]

    def _save_high_level_data(self, path: str) -> None:
        """Trajectories and labelled pairs, as npz (read back without pickle)."""
        self.preference_pipeline.save(sibling_path(path, ".high.npz"))

    def _load_high_level_data(self, path: str, truncate_last_traj: bool) -> Callable[[], None]:
        return self.preference_pipeline.read(sibling_path(path, ".high.npz"))
