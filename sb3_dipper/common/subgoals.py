"""Subgoal spaces: what part of an environment's achieved goal the higher level controls.

A higher-level action ``u`` lives in ``[-1, 1]^d``; :meth:`SubgoalSpace.to_world` maps it to a subgoal ``g`` in world
coordinates inside ``[low, high]``. The lower level is rewarded (sparse ``-1 / 0``) for bringing the projected
achieved goal within ``threshold`` of ``g``.

Env modules declare their space, either as an attribute ``subgoal_space`` of the unwrapped env or through
:func:`register_subgoal_space` for env ids we do not own. :func:`resolve_subgoal_space` finds it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv

from sb3_dipper.common.validation import InvalidSetting


@dataclass(frozen=True, eq=False)
class SubgoalSpace:
    """A box of subgoals over (a projection of) the achieved goal.

    :param low: lower corner of the subgoal box, in world coordinates
    :param high: upper corner of the subgoal box, in world coordinates
    :param threshold: distance under which the lower level has reached its subgoal
    :param indices: which entries of ``achieved_goal`` a subgoal controls (``None``: all of them)
    """

    low: np.ndarray
    high: np.ndarray
    threshold: float
    indices: tuple[int, ...] | None = None
    _span: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        low = np.asarray(self.low, dtype=np.float64).reshape(-1)
        high = np.asarray(self.high, dtype=np.float64).reshape(-1)
        if low.shape != high.shape:
            raise ValueError(f"SubgoalSpace low {low.shape} and high {high.shape} must have the same shape")
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high)) and np.all(high > low)):
            raise ValueError(f"SubgoalSpace needs finite bounds with high > low, got low={low}, high={high}")
        if self.indices is not None and len(self.indices) != low.size:
            raise ValueError(f"SubgoalSpace has {low.size} dimensions but {len(self.indices)} indices")
        if self.indices is not None and not (
            all(isinstance(index, (int, np.integer)) and index >= 0 for index in self.indices)
            and len(set(self.indices)) == len(self.indices)
        ):
            raise ValueError(
                f"SubgoalSpace indices must be distinct entries of the achieved goal (ints >= 0), got {self.indices}"
            )
        # NaN compares false with everything: every subgoal would count as reached.
        if not (isinstance(self.threshold, (int, float, np.number)) and math.isfinite(self.threshold) and self.threshold > 0):
            raise ValueError(f"SubgoalSpace threshold must be a finite number > 0, got {self.threshold!r}")
        object.__setattr__(self, "low", low)
        object.__setattr__(self, "high", high)
        object.__setattr__(self, "_span", high - low)

    @property
    def dim(self) -> int:
        return int(self.low.size)

    @property
    def unit_box(self) -> spaces.Box:
        """The higher-level action space."""
        return spaces.Box(-1.0, 1.0, shape=(self.dim,), dtype=np.float32)

    @property
    def world_box(self) -> spaces.Box:
        """The subgoal space in world coordinates (the lower level's ``desired_goal``)."""
        return spaces.Box(self.low.astype(np.float32), self.high.astype(np.float32), dtype=np.float32)

    def to_world(self, unit_actions: np.ndarray) -> np.ndarray:
        """Map higher-level actions in ``[-1, 1]^d`` to subgoals."""
        unit_actions = np.clip(unit_actions, -1.0, 1.0)
        return (self.low + 0.5 * (unit_actions + 1.0) * self._span).astype(np.float32)

    def to_world_tensor(self, unit_actions: th.Tensor) -> th.Tensor:
        """:meth:`to_world` for torch tensors, differentiable in ``unit_actions``."""
        low = th.as_tensor(self.low, dtype=unit_actions.dtype, device=unit_actions.device)
        span = th.as_tensor(self._span, dtype=unit_actions.dtype, device=unit_actions.device)
        return low + 0.5 * (unit_actions.clamp(-1.0, 1.0) + 1.0) * span

    def to_unit(self, subgoals: np.ndarray) -> np.ndarray:
        """Map subgoals back to ``[-1, 1]^d`` (clipped to the box)."""
        return np.clip(2.0 * (subgoals - self.low) / self._span - 1.0, -1.0, 1.0).astype(np.float32)

    def goal_unit_map(self, goal_mean: np.ndarray, goal_std: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(scale, shift, indices)`` such that the unit action of the goal ``goal_mean + goal_std * x`` (a goal
        normalised to ``x``) is ``clip(scale * x[indices] + shift, -1, 1)``: :meth:`to_unit` of :meth:`project` is
        affine per entry.

        :param goal_mean: per entry of the goal, the mean its normalisation subtracts (zeros for none)
        :param goal_std: per entry of the goal, the scale its normalisation divides by (ones for none)
        """
        indices = np.arange(self.dim) if self.indices is None else np.asarray(self.indices)
        mean, std = np.asarray(goal_mean, dtype=np.float64)[indices], np.asarray(goal_std, dtype=np.float64)[indices]
        return 2.0 * std / self._span, 2.0 * (mean - self.low) / self._span - 1.0, indices

    def project(self, achieved_goal: np.ndarray) -> np.ndarray:
        """The part of an achieved goal that a subgoal controls."""
        if self.indices is None:
            return achieved_goal
        return achieved_goal[..., list(self.indices)]

    def distance(self, achieved_subgoal: np.ndarray, subgoal: np.ndarray) -> np.ndarray:
        return np.linalg.norm(np.asarray(achieved_subgoal) - np.asarray(subgoal), axis=-1)

    def compute_reward(self, achieved_subgoal: np.ndarray, subgoal: np.ndarray, _info: Any = None) -> np.ndarray:
        """Sparse lower-level reward, vectorised over the leading dimensions: 0 when reached, -1 otherwise."""
        return -(self.distance(achieved_subgoal, subgoal) > self.threshold).astype(np.float32)

    def same_as(self, other: SubgoalSpace) -> bool:
        """Whether ``other`` is the same space: the same class and the same value of every field (box, threshold,
        indices, and a subclass's own fields)."""
        return type(other) is type(self) and all(
            _same_field(getattr(self, item.name), getattr(other, item.name)) for item in fields(self) if item.init
        )

    def describe(self) -> str:
        """The box and threshold, for messages: ``low=[-3.5, -3.5], high=[3.5, 3.5], threshold 0.45``."""
        indices = "" if self.indices is None else f", over achieved-goal entries {list(self.indices)}"
        return f"low={self.low.tolist()}, high={self.high.tolist()}, threshold {self.threshold:g}{indices}"


def _same_field(first: Any, second: Any) -> bool:
    if isinstance(first, SubgoalSpace) and isinstance(second, SubgoalSpace):
        return first.same_as(second)
    if isinstance(first, np.ndarray) or isinstance(second, np.ndarray):
        return bool(np.array_equal(np.asarray(first), np.asarray(second)))
    return bool(first == second)


@dataclass(frozen=True, eq=False)
class ElementSubgoalSpace(SubgoalSpace):
    """Subgoals that ask, for each task element, "done" or "as at the start", as the authors' kitchen code does.

    The achieved goal is split into task elements (a microwave hinge, a burner knob and slide, ...). The higher level
    still acts in ``[-1, 1]^d``, but a subgoal asks each element for one of two things: its entries equal the
    element's goal (``done``) when the unit action of the element's first entry is positive, else its start values
    (``start``). The authors' PIPER code binarises its 30-D kitchen subgoal this way (per element, the goal or zero),
    so a subgoal says which elements to have done, not where in between. An element is reached when it is within
    ``threshold`` of its subgoal values (the env's per-element completion test), and a subgoal when every element is:
    :meth:`distance` is the largest element distance.

    :meth:`to_world_tensor` passes gradients straight through the snapping, as through :meth:`SubgoalSpace.to_world`,
    so losses that differentiate a lower value with respect to the proposal (DIPPER's value term) still can.

    :param elements: the entries of each element, together every entry once
    :param done: the subgoal values of a done element, one per entry (the task's goal)
    :param start: the subgoal values of an element not asked for, one per entry (its reset values)
    """

    elements: tuple[tuple[int, ...], ...] = ()
    done: np.ndarray = field(default_factory=lambda: np.zeros(0))
    start: np.ndarray = field(default_factory=lambda: np.zeros(0))
    _first_entries: np.ndarray = field(init=False, repr=False)
    _owner: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        super().__post_init__()
        elements = tuple(tuple(int(entry) for entry in element) for element in self.elements)
        if not elements or any(not element for element in elements):
            raise ValueError(f"ElementSubgoalSpace elements must be non-empty groups of entries, got {self.elements}")
        if sorted(entry for element in elements for entry in element) != list(range(self.dim)):
            raise ValueError(f"ElementSubgoalSpace elements {elements} must hold every entry 0..{self.dim - 1} exactly once")
        for name in ("done", "start"):
            values = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            if values.shape != (self.dim,) or np.any(values < self.low) or np.any(values > self.high):
                raise ValueError(
                    f"ElementSubgoalSpace {name} must be {self.dim} values inside [low, high], got {getattr(self, name)}"
                )
            object.__setattr__(self, name, values)
        object.__setattr__(self, "elements", elements)
        object.__setattr__(self, "_first_entries", np.array([element[0] for element in elements]))
        owner = np.empty(self.dim, dtype=np.int64)
        for index, element in enumerate(elements):
            owner[list(element)] = index
        object.__setattr__(self, "_owner", owner)

    def _asked_done(self, unit_actions: np.ndarray) -> np.ndarray:
        """Per entry: is its element asked to be done?"""
        return (unit_actions[..., self._first_entries] > 0.0)[..., self._owner]

    def to_world(self, unit_actions: np.ndarray) -> np.ndarray:
        asked_done = self._asked_done(np.asarray(unit_actions))
        return np.where(asked_done, self.done, self.start).astype(np.float32)

    def to_world_tensor(self, unit_actions: th.Tensor) -> th.Tensor:
        continuous = super().to_world_tensor(unit_actions)
        first_entries = th.as_tensor(self._first_entries, device=unit_actions.device)
        owner = th.as_tensor(self._owner, device=unit_actions.device)
        asked_done = (unit_actions.index_select(-1, first_entries) > 0.0).index_select(-1, owner)
        done, start = (
            th.as_tensor(value, dtype=unit_actions.dtype, device=unit_actions.device) for value in (self.done, self.start)
        )
        snapped = th.where(asked_done, done, start)
        return continuous + (snapped - continuous).detach()

    def to_unit(self, subgoals: np.ndarray) -> np.ndarray:
        """The unit action whose subgoal asks done exactly for the elements done in ``subgoals``: +1 or -1 per entry."""
        element_done = self._element_distances(subgoals, self.done) < self.threshold
        return np.where(element_done[..., self._owner], 1.0, -1.0).astype(np.float32)

    def goal_unit_map(self, goal_mean: np.ndarray, goal_std: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        raise NotImplementedError(
            "ElementSubgoalSpace snaps each element to done or start, so a goal's unit action is not an affine map of the "
            "goal: a goal-anchored higher policy (policy_kwargs goal_anchored=True) cannot take this subgoal space"
        )

    def distance(self, achieved_subgoal: np.ndarray, subgoal: np.ndarray) -> np.ndarray:
        return np.max(self._element_distances(achieved_subgoal, subgoal), axis=-1)

    def _element_distances(self, first: np.ndarray, second: np.ndarray) -> np.ndarray:
        """Per element, the Euclidean distance over its entries: shape ``(..., len(elements))``."""
        difference = np.asarray(first, dtype=np.float64) - np.asarray(second, dtype=np.float64)
        return np.stack([np.linalg.norm(difference[..., list(element)], axis=-1) for element in self.elements], axis=-1)


SubgoalSpaceFactory = Callable[[gym.Env], SubgoalSpace]
_REGISTRY: dict[str, SubgoalSpaceFactory] = {}


def register_subgoal_space(env_id: str, factory: SubgoalSpaceFactory) -> None:
    """Declare the subgoal space of an env id that does not carry a ``subgoal_space`` attribute itself."""
    _REGISTRY[env_id] = factory


def registered_subgoal_space(env_id: str) -> SubgoalSpaceFactory | None:
    return _REGISTRY.get(env_id)


def _default_from_goal_space(goal_space: spaces.Box, threshold: float | None) -> SubgoalSpace | None:
    if threshold is None or not (np.all(np.isfinite(goal_space.low)) and np.all(np.isfinite(goal_space.high))):
        return None
    return SubgoalSpace(goal_space.low, goal_space.high, threshold)


def check_subgoal_space(subgoal_space: Any, observation_space: spaces.Space) -> None:
    """Refuse a subgoal space that does not fit the goal env's achieved goal, naming ``subgoal_space``: another type,
    indices beyond the achieved goal, or (a plain box) another dimension than the part of it the subgoals control.
    Torch or numpy would only fail at the first prediction, naming neither.

    :param subgoal_space: the space given to (or found for) a model
    :param observation_space: the env's ``Dict`` observation space, with its ``achieved_goal``
    """
    if not isinstance(subgoal_space, SubgoalSpace):
        raise InvalidSetting(
            "subgoal_space",
            f"subgoal_space must be a sb3_dipper.common.subgoals.SubgoalSpace (its box, threshold and indices), "
            f"got {type(subgoal_space).__name__}",
        )
    goal_size = int(np.prod(observation_space["achieved_goal"].shape))  # type: ignore[index]
    indices = subgoal_space.indices
    if indices is not None and max(indices) >= goal_size:
        raise InvalidSetting(
            "subgoal_space",
            f"subgoal_space indices {indices} reach beyond the env's achieved_goal of {goal_size} entries",
        )
    controlled = goal_size if indices is None else len(indices)
    # A subclass (RAPS's primitives, the kitchen's elements) lays out its dimensions its own way.
    if type(subgoal_space) is SubgoalSpace and subgoal_space.dim != controlled:
        raise InvalidSetting(
            "subgoal_space",
            f"subgoal_space has {subgoal_space.dim} dimensions, but its subgoals control {controlled} entries of the "
            f"env's achieved_goal ({goal_size} entries): give a box of {controlled} dimensions, or indices= naming "
            f"the {subgoal_space.dim} entries it controls",
        )


def resolve_subgoal_space(venv: VecEnv, subgoal_space: SubgoalSpace | None = None) -> SubgoalSpace:
    """Find the subgoal space of a vectorised goal env.

    Order: the one given, the env's ``subgoal_space`` attribute, the registry (by env id), and last a box over the
    ``achieved_goal`` bounds with the env's ``distance_threshold`` when both are finite.
    """
    if subgoal_space is not None:
        return subgoal_space
    if venv.has_attr("subgoal_space"):
        declared = venv.get_attr("subgoal_space", indices=[0])[0]
        if isinstance(declared, SubgoalSpace):
            return declared
    spec = venv.get_attr("spec", indices=[0])[0]
    env_id = getattr(spec, "id", None)
    factory = registered_subgoal_space(env_id) if env_id is not None else None
    if factory is not None:
        return factory(venv.get_attr("unwrapped", indices=[0])[0])
    goal_space = venv.observation_space["achieved_goal"]  # type: ignore[index]
    threshold = venv.get_attr("distance_threshold", indices=[0])[0] if venv.has_attr("distance_threshold") else None
    default = _default_from_goal_space(goal_space, threshold)
    if default is not None:
        return default
    # Say which of the two things the default needs is missing: each has its own fix.
    missing = []
    if not (np.all(np.isfinite(goal_space.low)) and np.all(np.isfinite(goal_space.high))):
        missing.append(
            f"its achieved_goal space is unbounded (low={goal_space.low}, high={goal_space.high}), so give the "
            "subgoal box's low and high (the region the agent's achieved goals can reach)"
        )
    if threshold is None:
        missing.append(
            "the env has no `distance_threshold` attribute, so give the threshold under which a subgoal counts as "
            "reached (or give the env a `distance_threshold`)"
        )
    raise ValueError(
        f"No subgoal space is known for env {env_id!r}: {'; and '.join(missing)}. "
        "Pass `subgoal_space=SubgoalSpace(low, high, threshold)` to the algorithm, give the env a `subgoal_space` "
        "attribute, or call `sb3_dipper.register_subgoal_space(env_id, factory)`."
    )
