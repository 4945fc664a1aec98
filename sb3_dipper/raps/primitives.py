"""RAPS's lower level: a library of scripted, closed-loop primitives, and the registry of libraries per env id.

A RAPS action is ``[arguments..., selector]`` in ``[-1, 1]^(A + 1)`` (Dalal et al., NeurIPS 2021, Section 3: a
primitive and its arguments per decision). The selector picks a primitive (:func:`select_primitive`: ``[-1, 1]`` cut
into equal bins, one per primitive in library order), the arguments are mapped to the library's argument box, and the
chosen primitive runs for the option's K primitive steps, recomputing its action from each new observation.

The maze and Fetch libraries follow the DIPPER authors' RAPS baseline (much smaller than the RAPS paper's twelve
primitives); the kitchen's does not (below):

====================================================  ========================================================================
env id                                                primitives (in selector order)
====================================================  ========================================================================
``PointMazeFourRooms-v0``                             ``reach`` (the maze's PD reach, :func:`.reach_action`)
``FetchPush-v4``, ``FetchPickAndPlace-v4``            ``close_gripper``, ``reach``, ``open_gripper`` (authors' selector signs)
``FetchPushFixed-v0``, ``FetchPickAndPlaceFixed-v0``  the same three
``FetchReach-v4``, ``FetchFourRoomMaze-v0``           ``reach`` (the authors' maze: goTo only)
``FrankaKitchenMicrowaveBurner-v0``                   ``joint_target`` (the 9 robot joints; our own controller)
any other env                                         ``reach``: P-control of ``observation[:d]`` with ``action[:d]``
====================================================  ========================================================================

``reach`` targets a position in the env's subgoal box (``d`` = its dimension). On Fetch the controlled point is the
gripper (the observation's first 3 entries) and the gripper entry of the action stays 0, which holds the fingers
(Fetch's finger actuators take targets relative to the current opening); ``open_gripper``/``close_gripper`` hold the
arm and drive the fingers. Other envs declare theirs with :func:`register_primitive_library`.

The kitchen's ``joint_target`` is a joint-target controller of our own (proportional joint velocities toward a 9-dim
joint-space target). It follows neither the DIPPER paper, which says its kitchen baseline uses the action primitives of
RAPS (its library of parameterised end-effector primitives), nor the authors' code (``Utsavz/piper``,
``--raps=1``), which uses the first 9 dimensions of the higher level's subgoal directly as the action at every step,
without a controller. Kitchen results of this RAPS are therefore not the paper's RAPS baseline.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np
from gymnasium import spaces

from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.envs.point_maze import reach_action

# The Franka's joint ranges in FrankaKitchen-v1 (gymnasium-robotics' kitchen_franka/franka_assets/chain.xml): 7 arm
# joints in radians, 2 finger joints in metres.
FRANKA_JOINT_LOW = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -1.6573, -2.8973, 0.0, 0.0])
FRANKA_JOINT_HIGH = np.array([2.8973, 1.7628, 2.8973, -0.4, 2.8973, 2.1127, 2.8973, 0.04, 0.04])


class Primitive(Protocol):
    """A scripted controller: primitive actions from observations and world-coordinate arguments (batched)."""

    @property
    def name(self) -> str:
        """The primitive's name (unique within a library)."""

    def __call__(self, observation: np.ndarray, arguments: np.ndarray) -> np.ndarray:
        """``(N, action_dim)`` actions for ``(N, obs_dim)`` observations and ``(N, A)`` arguments."""


@dataclass(frozen=True)
class Reach:
    """Proportional control of the point ``observation[:, :dims]`` toward ``arguments[:, :dims]`` through ``action[:, :dims]``.

    :param dims: dimension of the controlled point (the subgoal dimension)
    :param action_dim: dimension of the primitive action (entries past ``dims`` stay 0)
    :param gain: proportional gain (the DIPPER authors' goTo: 6)
    """

    dims: int
    action_dim: int
    gain: float = 6.0
    name: ClassVar[str] = "reach"

    def __call__(self, observation: np.ndarray, arguments: np.ndarray) -> np.ndarray:
        actions = np.zeros((observation.shape[0], self.action_dim), dtype=np.float32)
        actions[:, : self.dims] = np.clip(self.gain * (arguments[:, : self.dims] - observation[:, : self.dims]), -1.0, 1.0)
        return actions


@dataclass(frozen=True)
class MazeReach:
    """The point maze's reach: a PD force from the ball's position and velocity toward the argument position."""

    name: ClassVar[str] = "reach"

    def __call__(self, observation: np.ndarray, arguments: np.ndarray) -> np.ndarray:
        return reach_action(observation[:, :2], observation[:, 2:4], arguments[:, :2])


@dataclass(frozen=True)
class Gripper:
    """Open or close a Fetch gripper (the action's last entry) while the arm holds still.

    :param opening: open (``+1``) or close (``-1``)
    :param action_dim: dimension of the primitive action
    """

    opening: bool
    action_dim: int

    @property
    def name(self) -> str:
        return "open_gripper" if self.opening else "close_gripper"

    def __call__(self, observation: np.ndarray, arguments: np.ndarray) -> np.ndarray:
        actions = np.zeros((observation.shape[0], self.action_dim), dtype=np.float32)
        actions[:, -1] = 1.0 if self.opening else -1.0
        return actions


@dataclass(frozen=True)
class JointTarget:
    """Proportional joint-velocity control toward a joint-space target (Franka kitchen: ``observation[:9]`` are joints).

    Our own kitchen primitive, neither the RAPS paper's nor the DIPPER authors' (see the module docstring).

    :param joints: number of controlled joints (the first entries of observation and action)
    :param gain: proportional gain on the joint error, per unit of normalised velocity action (the kitchen scales an
        action of 1 to 2 rad/s, so at 12.5 steps per second a gain of 5 closes 80 % of the error per step)
    """

    joints: int = 9
    gain: float = 5.0
    name: ClassVar[str] = "joint_target"

    def __call__(self, observation: np.ndarray, arguments: np.ndarray) -> np.ndarray:
        errors = arguments[:, : self.joints] - observation[:, : self.joints]
        return np.clip(self.gain * errors, -1.0, 1.0).astype(np.float32)


@dataclass(frozen=True, eq=False)
class PrimitiveLibrary:
    """The primitives a RAPS higher level chooses from and the box their arguments live in.

    :param primitives: the primitives, in selector order
    :param argument_low: lower corner of the argument box (world coordinates), shape ``(A,)``
    :param argument_high: upper corner of the argument box
    :param positional: whether the first arguments are a position in the env's subgoal space (``reach``), so that the
        distance between them and the achieved subgoal is meaningful (``rollout/subgoal_distance``)
    """

    primitives: tuple[Primitive, ...]
    argument_low: np.ndarray
    argument_high: np.ndarray
    positional: bool = True

    def __post_init__(self) -> None:
        if len(self.primitives) == 0:
            raise ValueError("A primitive library needs at least one primitive")
        if np.shape(self.argument_low) != np.shape(self.argument_high) or np.ndim(self.argument_low) != 1:
            raise ValueError(
                f"argument_low {np.shape(self.argument_low)} and argument_high {np.shape(self.argument_high)} must be "
                "vectors of the same length"
            )

    @property
    def names(self) -> list[str]:
        return [primitive.name for primitive in self.primitives]


def select_primitive(selectors: np.ndarray, n_primitives: int) -> np.ndarray:
    """The primitive each selector in ``[-1, 1]`` picks: ``[-1, 1]`` cut into ``n_primitives`` equal bins, in order."""
    bins = np.floor((np.clip(selectors, -1.0, 1.0) + 1.0) / 2.0 * n_primitives).astype(np.int64)
    return np.minimum(bins, n_primitives - 1)


def dispatch_primitives(library: PrimitiveLibrary, observation: np.ndarray, parameters: np.ndarray) -> np.ndarray:
    """The primitive actions of a batch of RAPS parameters ``[arguments (world coordinates)..., selector]``.

    :param library: the primitives
    :param observation: ``(N, obs_dim)`` env observations (the ``observation`` entry of a goal env)
    :param parameters: ``(N, A + 1)`` arguments and selector of each env's current primitive
    :return: ``(N, action_dim)`` actions, each from the primitive its selector picks
    """
    arguments = parameters[:, :-1]
    choices = select_primitive(parameters[:, -1], len(library.primitives))
    actions: np.ndarray | None = None
    for index in np.unique(choices):
        rows = choices == index
        chosen = library.primitives[index](observation[rows], arguments[rows])
        if actions is None:
            actions = np.zeros((observation.shape[0], chosen.shape[1]), dtype=np.float32)
        actions[rows] = chosen
    assert actions is not None
    return actions


@dataclass(frozen=True, eq=False)
class PrimitiveSpace(SubgoalSpace):
    """The option layer's view of RAPS actions: ``[arguments, selector]`` is the "subgoal" an option pursues.

    ``to_world`` maps the arguments to the library's box and leaves the selector in ``[-1, 1]``, so the recurrent state
    of ``predict`` carries the chosen primitive and its arguments. Achieved goals are projected with the env's subgoal
    space; the distance to a positional library's arguments feeds ``rollout/subgoal_distance`` (NaN otherwise).

    :param target: the env's subgoal space
    :param compared_dims: how many leading arguments are a position in ``target`` (0: none)
    """

    target: SubgoalSpace | None = None
    compared_dims: int = 0

    def project(self, achieved_goal: np.ndarray) -> np.ndarray:
        assert self.target is not None
        return self.target.project(achieved_goal)

    def distance(self, achieved_subgoal: np.ndarray, subgoal: np.ndarray) -> np.ndarray:
        if self.compared_dims == 0:
            return np.full(np.shape(subgoal)[:-1], np.nan)
        return np.linalg.norm(np.asarray(achieved_subgoal) - np.asarray(subgoal)[..., : self.compared_dims], axis=-1)


def primitive_space(library: PrimitiveLibrary, target: SubgoalSpace) -> PrimitiveSpace:
    """The option layer's space of a library's actions, with achieved goals projected by the env's ``target`` space."""
    compared_dims = target.dim if library.positional else 0
    if compared_dims > library.argument_low.size:
        raise ValueError(
            f"A positional library needs at least the subgoal's {target.dim} arguments, but it has {library.argument_low.size}"
        )
    return PrimitiveSpace(
        np.append(library.argument_low, -1.0),
        np.append(library.argument_high, 1.0),
        target.threshold,
        target=target,
        compared_dims=compared_dims,
    )


# ---------------------------------------------------------------------------------------------------- the registry

PrimitiveLibraryFactory = Callable[[SubgoalSpace, spaces.Box], PrimitiveLibrary]


def reach_library(subgoal_space: SubgoalSpace, action_space: spaces.Box) -> PrimitiveLibrary:
    """``reach`` only: proportional control of ``observation[:d]`` toward a point of the subgoal box through ``action[:d]``."""
    action_dim = int(action_space.shape[0])
    if action_dim < subgoal_space.dim:
        raise ValueError(
            f"The default RAPS reach moves observation[:{subgoal_space.dim}] with action[:{subgoal_space.dim}], but the "
            f"env's actions have {action_dim} dimensions. Register a primitive library for this env with "
            "sb3_dipper.raps.register_primitive_library(env_id, factory) or pass primitives=... to RAPS."
        )
    return PrimitiveLibrary((Reach(subgoal_space.dim, action_dim),), subgoal_space.low, subgoal_space.high)


def maze_library(subgoal_space: SubgoalSpace, action_space: spaces.Box) -> PrimitiveLibrary:
    return PrimitiveLibrary((MazeReach(),), subgoal_space.low, subgoal_space.high)


def fetch_gripper_library(subgoal_space: SubgoalSpace, action_space: spaces.Box) -> PrimitiveLibrary:
    """Close (selector < -1/3), reach (middle third), open (> 1/3): the signs of the authors' selector."""
    action_dim = int(action_space.shape[0])
    primitives = (
        Gripper(opening=False, action_dim=action_dim),
        Reach(3, action_dim),
        Gripper(opening=True, action_dim=action_dim),
    )
    return PrimitiveLibrary(primitives, subgoal_space.low, subgoal_space.high)


def kitchen_library(subgoal_space: SubgoalSpace, action_space: spaces.Box) -> PrimitiveLibrary:
    return PrimitiveLibrary((JointTarget(),), FRANKA_JOINT_LOW, FRANKA_JOINT_HIGH, positional=False)


_LIBRARIES: dict[str, PrimitiveLibraryFactory] = {
    "PointMazeFourRooms-v0": maze_library,
    "FetchPush-v4": fetch_gripper_library,
    "FetchPickAndPlace-v4": fetch_gripper_library,
    "FetchPushFixed-v0": fetch_gripper_library,
    "FetchPickAndPlaceFixed-v0": fetch_gripper_library,
    "FetchReach-v4": reach_library,
    "FetchFourRoomMaze-v0": reach_library,
    "FrankaKitchenMicrowaveBurner-v0": kitchen_library,
}


def register_primitive_library(env_id: str, factory: PrimitiveLibraryFactory) -> None:
    """Declare the primitives of an env id: ``factory(subgoal_space, action_space)`` builds its library."""
    _LIBRARIES[env_id] = factory


def primitive_library(env_id: str | None, subgoal_space: SubgoalSpace, action_space: spaces.Box) -> PrimitiveLibrary:
    """The registered library of ``env_id``, or ``reach`` only."""
    factory = _LIBRARIES.get(env_id, reach_library) if env_id is not None else reach_library
    return factory(subgoal_space, action_space)
