"""DIPPER's higher-level policy: a squashed-Gaussian actor over subgoals in ``[-1, 1]^d``, no critic.

It is SB3's SAC ``Actor`` (same parameterisation: MLP trunk, mean and log-std heads, log-std clipped to [-20, 2] or
from below at ``log_std_min``, ``tanh`` squashing), trained only by the DIPPER loss. :meth:`DIPPERPolicy.log_prob`
gives the log-density of stored actions, which the preference loss needs and SB3's actor does not offer. With
``goal_anchored`` the mean is an offset from the goal's action (:class:`GoalAnchor`).
"""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, CombinedExtractor, FlattenExtractor
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from stable_baselines3.common.utils import polyak_update
from stable_baselines3.sac.policies import LOG_STD_MAX, LOG_STD_MIN, Actor
from torch import nn

from sb3_dipper.common.losses import squashed_gaussian_log_prob

# Keeps the anchor's pre-tanh value finite for a goal on the boundary of the subgoal box (atanh(0.999) is about 3.8).
ANCHOR_EPSILON = 1e-3


class GoalAnchor(nn.Module):
    """The higher-level action whose subgoal is the env's goal, as a pre-``tanh`` value, from the (normalised)
    ``desired_goal`` the policy observes: ``atanh(clip(scale * desired_goal[indices] + shift))``.

    The map from the observed goal to its unit action is affine per subgoal entry (undo the ``VecNormalize``
    statistics, project, scale into the subgoal box), so its ``scale``, ``shift`` and ``indices`` are buffers that the
    algorithm sets (:meth:`DIPPERPolicy.set_goal_anchor`) whenever the statistics change; they are saved with the policy.

    :param subgoal_dim: the subgoal space's dimension
    """

    scale: th.Tensor
    shift: th.Tensor
    indices: th.Tensor

    def __init__(self, subgoal_dim: int) -> None:
        super().__init__()
        self.register_buffer("scale", th.zeros(subgoal_dim))
        self.register_buffer("shift", th.zeros(subgoal_dim))
        self.register_buffer("indices", th.arange(subgoal_dim))

    def forward(self, desired_goal: th.Tensor) -> th.Tensor:
        unit = self.scale * desired_goal.index_select(-1, self.indices) + self.shift
        return th.atanh(unit.clamp(-1.0 + ANCHOR_EPSILON, 1.0 - ANCHOR_EPSILON))


class FlooredStdActor(Actor):
    """SB3's SAC ``Actor`` whose log-std is clipped from below at ``log_std_min`` (SB3 clips at -20), and whose mean is
    optionally an offset from the goal's action (``goal_anchor``).

    A preference loss can widen a pair's margin by narrowing the policy instead of moving its mean: near SB3's floor
    a stored action off the mean has a log-density of order -1e15, and the loss is decided by the variance. A higher
    floor bounds every log-density ratio, so only where the mean lies can separate the trajectories.

    :param log_std_min: the lowest log-std (the default, SB3's, changes nothing)
    :param goal_anchor: when given, the pre-``tanh`` mean is the goal's action plus the network's output, whose last
        layer starts at zero: the untrained actor proposes the goal (the lower level driven by the goal)
    """

    def __init__(
        self, *args: Any, log_std_min: float = LOG_STD_MIN, goal_anchor: GoalAnchor | None = None, **kwargs: Any
    ) -> None:
        super().__init__(*args, **kwargs)
        self.log_std_min = log_std_min
        self.goal_anchor = goal_anchor
        self.start_at_the_anchor()

    def start_at_the_anchor(self) -> None:
        """With a goal anchor, zero the mean's last layer, so that the actor proposes the goal (its untrained state)."""
        if self.goal_anchor is not None:
            assert isinstance(self.mu, nn.Linear), "SAC's actor without gSDE: the mean is a linear layer"
            nn.init.zeros_(self.mu.weight)
            nn.init.zeros_(self.mu.bias)

    def offset_from_the_anchor(self, obs: PyTorchObs) -> th.Tensor:
        """The pre-``tanh`` mean's offset from the goal's action (the network's own output), shape ``(N, d)``."""
        assert self.goal_anchor is not None, "only a goal-anchored actor has an offset from the goal"
        return super().get_action_dist_params(obs)[0]

    def get_action_dist_params(self, obs: PyTorchObs) -> tuple[th.Tensor, th.Tensor, dict[str, th.Tensor]]:
        mean_actions, log_std, kwargs = super().get_action_dist_params(obs)
        if self.goal_anchor is not None:
            mean_actions = mean_actions + self.goal_anchor(obs["desired_goal"])  # type: ignore[index]
        return mean_actions, log_std.clamp(min=self.log_std_min), kwargs


class DIPPERPolicy(BasePolicy):
    """Squashed-Gaussian higher-level policy.

    In DIPPER, SB3's attribute ``model.policy`` is this higher level: ``model.policy.predict`` returns a higher-level
    action in ``[-1, 1]^d`` (a subgoal; ``model.subgoal_space.to_world`` maps it to the goal space), not a primitive
    action. ``model.predict`` runs both levels, and ``model.export_policy()`` returns them as a
    :class:`~sb3_dipper.common.hierarchical_policy.HierarchicalPolicy` that acts without the algorithm. (DPO-FLAT uses
    this class as a flat policy, whose actions are primitive actions.)

    :param observation_space: the base env's observation space (a goal env's Dict space)
    :param action_space: the higher-level action space ``[-1, 1]^d``
    :param lr_schedule: learning-rate schedule of the policy optimizer
    :param net_arch: hidden layer sizes of the actor
    :param activation_fn: activation function
    :param log_std_init: unused by the state-dependent log-std head; kept for SAC compatibility
    :param features_extractor_class: features extractor (default: ``CombinedExtractor`` for Dict spaces)
    :param features_extractor_kwargs: its keyword arguments
    :param normalize_images: whether to divide image observations by 255
    :param optimizer_class: optimizer class
    :param optimizer_kwargs: optimizer keyword arguments
    :param acting_tau: when below 1, the policy acts with a Polyak average of the trained actor (``tau`` per update)
    :param log_std_min: the lowest log-std of the actor (pre-``tanh``; SB3's is -20): a floor keeps the preference loss
        from separating trajectories by shrinking the variance (see :class:`FlooredStdActor`)
    :param goal_anchored: the actor's mean is an offset from the action whose subgoal is the observed goal, starting
        at zero (see :class:`GoalAnchor`): the untrained policy proposes the goal, and preferences teach it where to
        deviate. Needs Dict observations with ``desired_goal``; DIPPER sets the anchor's map from its subgoal space.
    """

    actor: FlooredStdActor
    averaged_actor: FlooredStdActor | None

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        net_arch: list[int] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        log_std_init: float = -3,
        features_extractor_class: type[BaseFeaturesExtractor] | None = None,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
        acting_tau: float = 1.0,
        log_std_min: float = LOG_STD_MIN,
        goal_anchored: bool = False,
    ):
        if features_extractor_class is None:
            features_extractor_class = CombinedExtractor if isinstance(observation_space, spaces.Dict) else FlattenExtractor
        super().__init__(
            observation_space,
            action_space,
            features_extractor_class,
            features_extractor_kwargs,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            squash_output=True,
            normalize_images=normalize_images,
        )
        if not 0.0 < acting_tau <= 1.0:
            raise ValueError(f"acting_tau must be in (0, 1], got {acting_tau}")
        if not (math.isfinite(log_std_min) and LOG_STD_MIN <= log_std_min < LOG_STD_MAX):
            raise ValueError(
                f"log_std_min must be a number in [{LOG_STD_MIN}, {LOG_STD_MAX}) (SB3's log-std bounds), got {log_std_min}"
            )
        self.net_arch = [256, 256] if net_arch is None else net_arch
        self.activation_fn = activation_fn
        self.log_std_init = log_std_init
        self.acting_tau = acting_tau
        self.log_std_min = float(log_std_min)
        if goal_anchored and not (isinstance(observation_space, spaces.Dict) and "desired_goal" in observation_space.spaces):
            raise ValueError(
                "policy_kwargs goal_anchored=True anchors the higher level's subgoals at the observed goal: it needs a "
                f"goal env's Dict observations with 'desired_goal', got {observation_space}"
            )
        self.goal_anchored = bool(goal_anchored)
        self._build(lr_schedule)

    def _build(self, lr_schedule: Schedule) -> None:
        features_extractor = self.make_features_extractor()
        self.actor = FlooredStdActor(
            self.observation_space,
            self.action_space,  # type: ignore[arg-type]
            net_arch=self.net_arch,
            features_extractor=features_extractor,
            features_dim=features_extractor.features_dim,
            activation_fn=self.activation_fn,
            normalize_images=self.normalize_images,
            log_std_min=self.log_std_min,
            goal_anchor=GoalAnchor(self.action_space.shape[0]) if self.goal_anchored else None,  # type: ignore[index]
        )
        self.actor.optimizer = self.optimizer_class(
            self.actor.parameters(),
            lr=lr_schedule(1),
            **self.optimizer_kwargs,  # type: ignore[call-arg]
        )
        # With acting_tau < 1 the policy acts with a slow Polyak average of the trained actor.
        self.averaged_actor = copy.deepcopy(self.actor).requires_grad_(False) if self.acting_tau < 1.0 else None

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            dict(
                net_arch=self.net_arch,
                activation_fn=self.activation_fn,
                log_std_init=self.log_std_init,
                features_extractor_class=self.features_extractor_class,
                features_extractor_kwargs=self.features_extractor_kwargs,
                optimizer_class=self.optimizer_class,
                optimizer_kwargs=self.optimizer_kwargs,
                acting_tau=self.acting_tau,
                log_std_min=self.log_std_min,
                goal_anchored=self.goal_anchored,
                lr_schedule=self._dummy_schedule,
            )
        )
        return data

    def log_prob(self, observation: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """Log-probability of stored higher-level actions under the trained actor, shape ``(N,)``."""
        mean_actions, log_std, _ = self.actor.get_action_dist_params(observation)
        return squashed_gaussian_log_prob(mean_actions, log_std, actions)

    def averaged_log_prob(self, observation: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """Log-probability of stored higher-level actions under the Polyak-averaged actor (needs ``acting_tau < 1``)."""
        if self.averaged_actor is None:
            raise ValueError("the policy keeps no averaged actor: set policy_kwargs acting_tau below 1")
        mean_actions, log_std, _ = self.averaged_actor.get_action_dist_params(observation)
        return squashed_gaussian_log_prob(mean_actions, log_std, actions)

    def sample_with_log_prob(self, observation: PyTorchObs) -> tuple[th.Tensor, th.Tensor]:
        """Reparameterised actions of the trained actor and their log-probabilities."""
        return self.actor.action_log_prob(observation)

    def set_goal_anchor(self, scale: np.ndarray, shift: np.ndarray, indices: np.ndarray) -> None:
        """Set the map from the observed ``desired_goal`` to the goal's action (``scale * goal[indices] + shift``, see
        :class:`GoalAnchor`) in the trained and the averaged actor."""
        for actor in (self.actor, self.averaged_actor):
            if actor is not None and actor.goal_anchor is not None:
                anchor = actor.goal_anchor
                anchor.scale.copy_(th.as_tensor(scale, dtype=anchor.scale.dtype))
                anchor.shift.copy_(th.as_tensor(shift, dtype=anchor.shift.dtype))
                anchor.indices.copy_(th.as_tensor(indices, dtype=anchor.indices.dtype))

    def update_averaged_actor(self) -> None:
        if self.averaged_actor is not None:
            polyak_update(self.actor.parameters(), self.averaged_actor.parameters(), self.acting_tau)

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self._predict(obs, deterministic=deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        acting = self.actor if self.averaged_actor is None else self.averaged_actor
        return acting(observation, deterministic)

    def set_training_mode(self, mode: bool) -> None:
        self.actor.set_training_mode(mode)
        self.training = mode


MlpPolicy = DIPPERPolicy
MultiInputPolicy = DIPPERPolicy
