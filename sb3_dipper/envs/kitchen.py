"""``FrankaKitchenMicrowaveBurner-v0``: gymnasium-robotics' Franka kitchen, open the microwave and then turn on the burner.

The robot must open the microwave door and then turn the bottom burner's knob (the bottom-left knob, ``knob_Joint_2``),
in that order, the kitchen task of the DIPPER paper. An episode is ``K x T = 15 x 15 = 225`` steps of gymnasium-robotics'
``FrankaKitchen-v1`` (``tasks_to_complete=["microwave", "bottom burner"]``): 9 joint velocities in ``[-1, 1]``
(float32 here, float64 upstream), 12.5 steps per simulated second, the upstream reset state, observation and noise.

Differences from the upstream env, all chosen so the task is a standard SB3 goal env:

- a flat observation ``Dict(observation, achieved_goal, desired_goal)`` of 1-D float64 boxes. ``achieved_goal`` is
  the (noise-free) positions of the task elements' joints, in task order, ``desired_goal`` their upstream goal values:
  ``[microwave hinge, bottom-burner knob, bottom-burner slide]`` = ``qpos[[22, 11, 12]]``, goal ``[-0.75, -0.88, -0.01]``;
- reward ``-1 / 0`` from a pure, vectorised ``compute_reward``: 0 iff every task element is within the upstream
  completion threshold (``BONUS_THRESH`` = 0.3, Euclidean norm over the element's joints) of its goal. It is a function
  of the goals alone, so it cannot see the order in which the elements were completed;
- the order enters ``info["is_success"]`` only (see :class:`FrankaKitchenOrderedEnv`): the episode counts as a success
  if both elements are complete and the microwave was completed first;
- no termination: the task stays solved (or not) until the time limit, as the paper measures success at the last step.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces
from gymnasium.utils.ezpickle import EzPickle
from gymnasium_robotics.envs.franka_kitchen.kitchen_env import (
    BONUS_THRESH,
    OBS_ELEMENT_GOALS,
    OBS_ELEMENT_INDICES,
    KitchenEnv,
)

from sb3_dipper.common.subgoals import ElementSubgoalSpace, SubgoalSpace

ENV_ID = "FrankaKitchenMicrowaveBurner-v0"
TASKS: tuple[str, ...] = ("microwave", "bottom burner")
# K x T = 15 x 15 primitive steps, as in the paper.
MAX_EPISODE_STEPS = 225
# Added on both sides of a joint's range (and of a goal outside it) for the subgoal box: MuJoCo's joint limits are
# soft, so a pushed joint ends slightly past them, and the bottom burner's slide goal (-0.01) lies outside its range
# [-0.009, 0].
SUBGOAL_MARGIN = 0.05


def _rotation_z(angle: float) -> np.ndarray:
    cos, sin = np.cos(angle), np.sin(angle)
    return np.array([[cos, -sin, 0.0], [sin, cos, 0.0], [0.0, 0.0, 1.0]])


def _rotation_y(angle: float) -> np.ndarray:
    cos, sin = np.cos(angle), np.sin(angle)
    return np.array([[cos, 0.0, sin], [0.0, 1.0, 0.0], [-sin, 0.0, cos]])


def joint_goal_bounds(
    model: mujoco.MjModel, tasks: Sequence[str], margin: float = SUBGOAL_MARGIN
) -> tuple[np.ndarray, np.ndarray]:
    """Box over the achieved goal of ``tasks``: each joint's range (stretched to contain its goal) plus ``margin``.

    :param model: the kitchen's MuJoCo model
    :param tasks: task elements, in achieved-goal order
    :param margin: added on both sides
    :return: ``low`` and ``high``, one entry per achieved-goal dimension
    """
    low, high = [], []
    for task in tasks:
        for address, goal in zip(OBS_ELEMENT_INDICES[task], OBS_ELEMENT_GOALS[task], strict=True):
            joints = np.flatnonzero(model.jnt_qposadr == address)
            one_dof = (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE)
            if joints.size != 1 or model.jnt_type[joints[0]] not in one_dof or not model.jnt_limited[joints[0]]:
                raise ValueError(f"Task {task!r}: qpos[{address}] is not a limited hinge or slide joint")
            joint_low, joint_high = model.jnt_range[joints[0]]
            low.append(min(joint_low, goal) - margin)
            high.append(max(joint_high, goal) + margin)
    return np.array(low), np.array(high)


class FrankaKitchenOrderedEnv(KitchenEnv):
    """Franka kitchen with flat goals, a sparse vectorised reward and success only for the task elements done in order.

    Observation: ``observation`` is upstream's 59 numbers (robot joint positions and velocities, object positions and
    velocities, with upstream's noise); ``achieved_goal`` concatenates the noise-free joint positions of the task
    elements (``OBS_ELEMENT_INDICES``) in task order and ``desired_goal`` their goals (``OBS_ELEMENT_GOALS``).

    Reward: ``compute_reward`` is 0 iff every element is within ``BONUS_THRESH`` (0.3, norm over the element's joints)
    of its goal, else -1. It depends on the goals only, so it is order-free: relabelled goals (HER) get the same reward
    whatever the order of completions, and the step reward is 0 in a state that has every element done, even in the
    wrong order.

    Success: let ``t_i`` be the first step of the episode at which element ``i`` is complete (step 0 is the reset state,
    step ``t`` the state after the ``t``-th action). ``info["is_success"]`` after step ``t`` is 1.0 iff every element is
    complete in the state after step ``t`` and ``t_1 < t_2 < ...`` in task order: for the default tasks, the microwave
    was opened (for the first time) at an earlier step than the one at which the bottom burner was first turned on, and
    both are open / on now. A burner turned on before the microwave was opened spoils the episode for good (turning it
    off and on again does not help: order is judged by first completions), and two elements first completed at the same
    step are not in order.

    The episode never terminates (upstream's ``terminate_on_tasks_completed`` is off); use a time limit.
    The unwrapped env carries ``subgoal_space``: a box over the achieved goal from the joints' ranges (see
    :func:`joint_goal_bounds`) with the completion threshold as its radius, or with ``element_subgoals`` the same box
    as an :class:`~sb3_dipper.common.subgoals.ElementSubgoalSpace`, whose subgoals are each element done or at rest.

    :param tasks: task elements in the order they must be completed (any upstream task with limited 1-dof joints, so
        not ``kettle``)
    :param element_subgoals: declare an :class:`~sb3_dipper.common.subgoals.ElementSubgoalSpace` instead of the box:
        a subgoal asks each task element to be done (its goal) or as at the start (its reset values), as the authors'
        PIPER code binarises its kitchen subgoals, rather than for any joint position in between
    :param kwargs: passed to gymnasium-robotics' ``KitchenEnv`` and its robot (``render_mode``, ``robot_noise_ratio``,
        ``object_noise_ratio``, ``frame_skip``, ``width``, ``height``, ...)
    """

    def __init__(self, tasks: Sequence[str] = TASKS, element_subgoals: bool = False, **kwargs: Any) -> None:
        tasks = tuple(tasks)
        if not tasks or len(set(tasks)) != len(tasks):
            raise ValueError(f"tasks must be a non-empty sequence without repetitions, got {tasks}")
        unknown = [task for task in tasks if task not in OBS_ELEMENT_GOALS]
        if unknown:
            raise ValueError(f"Unknown tasks {unknown}: choose from {sorted(OBS_ELEMENT_GOALS)}")
        super().__init__(
            tasks_to_complete=list(tasks), terminate_on_tasks_completed=False, remove_task_when_completed=False, **kwargs
        )
        # Upstream pickles (and copies) itself by calling its class with its own arguments: record ours instead.
        EzPickle.__init__(self, tasks=tasks, element_subgoals=element_subgoals, **kwargs)
        self.tasks = tasks
        self.completion_threshold = float(BONUS_THRESH)
        sizes = [len(OBS_ELEMENT_INDICES[task]) for task in tasks]
        offsets = np.cumsum([0, *sizes])
        self._goal_slices = [slice(int(start), int(stop)) for start, stop in itertools.pairwise(offsets)]
        self._desired_goal = np.concatenate([OBS_ELEMENT_GOALS[task] for task in tasks]).astype(np.float64)
        goal_dim = int(offsets[-1])
        # Upstream's observation: robot joint positions and velocities (9 + 9), object positions and velocities.
        observation_dim = self.model.nq + self.model.nv
        self.observation_space = spaces.Dict(
            {
                "observation": spaces.Box(-np.inf, np.inf, shape=(observation_dim,), dtype=np.float64),
                "achieved_goal": spaces.Box(-np.inf, np.inf, shape=(goal_dim,), dtype=np.float64),
                "desired_goal": spaces.Box(-np.inf, np.inf, shape=(goal_dim,), dtype=np.float64),
            }
        )
        # Upstream's actions are float64; SB3 works in float32 (the robot clips and converts them either way).
        self.action_space = spaces.Box(-1.0, 1.0, shape=(self.model.nu,), dtype=np.float32)
        low, high = joint_goal_bounds(self.model, tasks)
        if not element_subgoals:
            self.subgoal_space = SubgoalSpace(low=low, high=high, threshold=self.completion_threshold)
        else:
            start = np.concatenate([self.robot_env.init_qpos[OBS_ELEMENT_INDICES[task]] for task in tasks])
            self.subgoal_space = ElementSubgoalSpace(
                low=low,
                high=high,
                threshold=self.completion_threshold,
                elements=tuple(tuple(range(part.start, part.stop)) for part in self._goal_slices),
                done=self._desired_goal,
                start=start,
            )
        self._steps = 0
        self._first_completion: list[int | None] = [None] * len(tasks)

    # --- goals and rewards -----------------------------------------------------------------------------------------

    def task_completions(self, achieved_goal: np.ndarray, desired_goal: np.ndarray) -> np.ndarray:
        """Which task elements are complete, vectorised over the leading dimensions: shape ``(..., len(tasks))``."""
        achieved_goal, desired_goal = np.asarray(achieved_goal), np.asarray(desired_goal)
        distances = [np.linalg.norm(achieved_goal[..., part] - desired_goal[..., part], axis=-1) for part in self._goal_slices]
        return np.stack(distances, axis=-1) < self.completion_threshold

    def compute_reward(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any = None) -> np.ndarray:
        """Sparse reward, vectorised over the leading dimensions: 0 if every task element is complete, -1 otherwise.

        A pure function of the goals: it does not know (or change) the order of completions in the episode.
        """
        return -(~np.all(self.task_completions(achieved_goal, desired_goal), axis=-1)).astype(np.float64)

    def compute_terminated(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any = None) -> bool:
        """Never: the episode runs to its time limit."""
        return False

    def compute_truncated(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any = None) -> bool:
        """Never here: the time limit is gymnasium's ``TimeLimit`` wrapper."""
        return False

    # --- episode ---------------------------------------------------------------------------------------------------

    def _flat_observation(self, upstream_observation: dict[str, Any]) -> dict[str, np.ndarray]:
        achieved = upstream_observation["achieved_goal"]
        return {
            "observation": np.array(upstream_observation["observation"], dtype=np.float64),
            "achieved_goal": np.concatenate([achieved[task] for task in self.tasks]).astype(np.float64),
            "desired_goal": self._desired_goal.copy(),
        }

    def _update_order(self, achieved_goal: np.ndarray) -> dict[str, Any]:
        """Record first completions at the current step; return the info with ``is_success``."""
        complete = self.task_completions(achieved_goal, self._desired_goal)
        for index, done in enumerate(complete):
            if done and self._first_completion[index] is None:
                self._first_completion[index] = self._steps
        firsts = self._first_completion
        in_order = all(
            first is not None and later is not None and first < later for first, later in itertools.pairwise(firsts)
        )
        completed = sorted((step, index) for index, step in enumerate(firsts) if step is not None)
        return {
            "is_success": float(bool(np.all(complete)) and in_order),
            "episode_task_completions": [self.tasks[index] for _, index in completed],
        }

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict[str, np.ndarray], dict]:
        upstream_observation, _ = super().reset(seed=seed, options=options)
        obs = self._flat_observation(upstream_observation)
        self._steps = 0
        self._first_completion = [None] * len(self.tasks)
        return obs, self._update_order(obs["achieved_goal"])

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        # Upstream's step removes completed tasks and calls its state-mutating reward: drive the robot directly.
        robot_observation, *_ = self.robot_env.step(action)
        obs = self._flat_observation(self._get_obs(robot_observation))
        self._steps += 1
        info = self._update_order(obs["achieved_goal"])
        reward = float(self.compute_reward(obs["achieved_goal"], obs["desired_goal"], info))
        return obs, reward, False, False, info


# ------------------------------------------------------------------------------------------------------------------
# Scripted expert
# ------------------------------------------------------------------------------------------------------------------

# Arm postures the expert travels through in joint space (found offline by inverse kinematics with random restarts,
# keeping the ones furthest from the joint limits). The upstream reset posture is folded backwards with joint 2 at its
# limit: a Cartesian controller cannot unfold it, a joint-space move can.
# In front of the microwave handle, gripper ready to grasp it (see HANDLE_YAW and HANDLE_PITCH).
MICROWAVE_READY = np.array([1.105, 0.95, -0.036, -1.406, -1.118, 0.85, -1.197])
# Beside the open door, right of its edge: going straight from the door to the knob would sweep it shut.
TRANSIT = np.array([2.09, 0.54, -0.1, -2.06, -1.17, -0.18, -0.52])
# In front of the bottom-left knob, gripper level and pointing at it, joint 7 with a turn of room to spare.
KNOB_READY = np.array([1.02, -0.24, -0.42, -2.44, -2.32, 0.67, -0.7])

# Gripper orientation on the handle, in the door's frame: the gripper points into the door (door y axis) with its
# fingers across the vertical bar, pitched 0.8 rad down (reachable with a margin to the joint limits), yawed 0.3 rad
# towards the door's free edge so that it pulls partly against a finger rather than through friction alone (square to
# the door, the bar creeps out of the fingers before the door is open), and rolled half a turn so that its joint 7 ends
# near the knob posture's.
HANDLE_YAW, HANDLE_PITCH = -0.3, -0.8
# Gripper orientation on the knob (columns: gripper x, y, z in the world): pointing at the knob (+y), fingers across
# the knob's vertical bar, rolled half a turn as on the handle.
KNOB_GRASP = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])


class FrankaKitchenMicrowaveBurnerExpert:
    """Scripted expert for ``FrankaKitchenMicrowaveBurner-v0``: open the microwave, then turn on the bottom burner.

    It reads the (noise-free) simulator state of ``env.unwrapped``, not the observation, and goes through fixed stages,
    each ending on a geometric condition or a step budget:

    1. a joint-space move to a posture in front of the microwave handle (the reset posture cannot be unfolded by a
       Cartesian controller);
    2. operational-space control of the end-effector site (damped least squares on the site Jacobian from
       ``mujoco.mj_jacSite``): to 10 cm in front of the handle, onto the handle, close the gripper;
    3. pull along the door's arc: every step the target is the handle rotated 0.15 rad further about the hinge, the
       gripper orientation turning with the door, until the door is at -0.6 rad (goal -0.75, completion within 0.3);
    4. open the gripper, back away from the handle, travel in joint space past the door's edge to a posture in front of
       the knob;
    5. onto the knob's bar, close, turn the gripper about the knob's axis, 0.15 rad ahead of its current angle, until
       the knob is at -0.8 rad (goal -0.88; it ends near -0.9 as the gripper stops), open and back away.

    Joint commands are turned into actions through upstream's velocity-to-position mapping: the action ``a`` moves the
    joint position servos' targets to ``q + (act_mid + act_rng * a) * dt``. Commands add the gravity torque divided by
    the servo gain, since a zero action otherwise sags under gravity.

    :param env: a ``FrankaKitchenMicrowaveBurner-v0`` env (or its unwrapped env)
    """

    # Fraction of a commanded joint step the position servos achieve within one env step (0.08 s); commands are
    # divided by it so the arm moves about as far as asked.
    servo_tracking = 0.6
    # Largest end-effector step per env step (metres) and rotation (radians) the operational-space controller asks for.
    max_step = 0.03
    max_rotation = 0.12
    # Largest joint step (radians) of a joint-space move.
    max_joint_step = 0.1
    # Damping of the least-squares inverse and pull of the null space towards the stage's posture.
    damping = 0.03
    posture_gain = 0.05
    # Kept from the joint limits.
    joint_margin = 0.05
    # Door and knob angles at which the expert lets go (upstream goals -0.75 and -0.88, both met within 0.3).
    door_open_angle = -0.6
    knob_on_angle = -0.8
    # Grasping the knob: the end-effector site 4.2 cm in front of the knob's bar centre puts the fingertips just short
    # of the knob's base plate.
    knob_grasp_depth = 0.042
    # Every stage ends after this many steps at the latest, so the expert never waits forever on a missed tolerance.
    stage_budget = 60

    def __init__(self, env: gym.Env) -> None:
        kitchen = env.unwrapped
        if tuple(getattr(kitchen, "tasks", ())) != TASKS:
            raise ValueError(f"{type(self).__name__} solves the tasks {TASKS}, the env has {getattr(kitchen, 'tasks', None)}")
        self.model: mujoco.MjModel = kitchen.model  # type: ignore[attr-defined]
        self.data: mujoco.MjData = kitchen.data  # type: ignore[attr-defined]
        robot = kitchen.robot_env  # type: ignore[attr-defined]
        self._dt = float(robot.dt)
        self._act_mid, self._act_rng = np.asarray(robot.act_mid[:7]), np.asarray(robot.act_rng[:7])
        self._gain = self.model.actuator_gainprm[:7, 0].copy()
        self._low = self.model.jnt_range[:7, 0] + self.joint_margin
        self._high = self.model.jnt_range[:7, 1] - self.joint_margin
        self._site = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, "end_effector")
        self._handle = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, "microhandle_site")
        self._knob = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, "knob2_site")
        self._door = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, "microdoorroot")
        self._door_qpos = int(OBS_ELEMENT_INDICES["microwave"][0])
        self._knob_qpos = int(OBS_ELEMENT_INDICES["bottom burner"][0])
        self._jacp = np.zeros((3, self.model.nv))
        self._jacr = np.zeros((3, self.model.nv))
        self._stages: list[Callable[[], tuple[np.ndarray, bool]]] = [
            self._to_microwave,
            self._before_handle,
            self._onto_handle,
            self._grasp_handle,
            self._pull_door,
            self._release_handle,
            self._back_off_handle,
            self._to_transit,
            self._to_knob,
            self._before_knob,
            self._onto_knob,
            self._grasp_knob,
            self._turn_knob,
            self._release_knob,
            self._back_off_knob,
        ]
        self.reset()

    def reset(self) -> None:
        """Start an episode at the first stage."""
        self._stage = 0
        self._stage_steps = 0
        self._posture = MICROWAVE_READY

    @property
    def stage(self) -> str:
        """Name of the current stage."""
        return self._stages[self._stage].__name__.lstrip("_")

    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        """The expert action for the current state (the observation is not used: the expert reads the simulator)."""
        action, done = self._stages[self._stage]()
        self._stage_steps += 1
        if (done or self._stage_steps >= self.stage_budget) and self._stage < len(self._stages) - 1:
            self._stage += 1
            self._stage_steps = 0
        return action

    # --- geometry --------------------------------------------------------------------------------------------------

    @property
    def _position(self) -> np.ndarray:
        return self.data.site_xpos[self._site].copy()

    @property
    def _orientation(self) -> np.ndarray:
        return self.data.site_xmat[self._site].reshape(3, 3).copy()

    def _handle_grasp(self) -> np.ndarray:
        """Gripper orientation on the handle, which turns with the door."""
        door = self.data.xmat[self._door].reshape(3, 3)
        points_into_door = np.column_stack([door[:, 2], door[:, 0], door[:, 1]])
        return _rotation_z(HANDLE_YAW) @ points_into_door @ _rotation_y(HANDLE_PITCH) @ _rotation_z(np.pi)

    def _before_handle_target(self) -> np.ndarray:
        return self.data.site_xpos[self._handle] - 0.1 * self._handle_grasp()[:, 2]

    def _knob_target(self, depth: float) -> np.ndarray:
        return self.data.site_xpos[self._knob] - np.array([0.0, depth, 0.0])

    def _near(self, target: np.ndarray, tolerance: float, orientation: np.ndarray | None = None) -> bool:
        close = float(np.linalg.norm(target - self._position)) < tolerance
        if orientation is None:
            return close
        return close and float(np.linalg.norm(_orientation_error(self._orientation, orientation))) < 0.05

    # --- commands --------------------------------------------------------------------------------------------------

    def _action(self, joint_step: np.ndarray, grip: float) -> np.ndarray:
        """Action for an arm joint step (radians this env step) and a gripper command (+1 open, -1 close)."""
        target_step = joint_step / self.servo_tracking + self.data.qfrc_bias[:7] / self._gain
        action = np.empty(9)
        action[:7] = (target_step / self._dt - self._act_mid) / self._act_rng
        action[7:] = grip
        return np.clip(action, -1.0, 1.0).astype(np.float32)

    def _joint_move(self, posture: np.ndarray, tolerance: float, grip: float = 1.0) -> tuple[np.ndarray, bool]:
        """Straight line in joint space towards ``posture``, all joints arriving together."""
        error = posture - self.data.qpos[:7]
        largest = float(np.max(np.abs(error)))
        step = error * min(1.0, self.max_joint_step / max(largest, 1e-9))
        return self._action(step, grip), largest < tolerance

    def _reach(self, target: np.ndarray, orientation: np.ndarray, grip: float, max_step: float | None = None) -> np.ndarray:
        """Operational-space step of the end-effector site towards a pose, joints kept off their limits."""
        translation = _clip_norm(target - self._position, self.max_step if max_step is None else max_step)
        rotation = _clip_norm(_orientation_error(self._orientation, orientation), self.max_rotation)
        mujoco.mj_jacSite(self.model, self.data, self._jacp, self._jacr, self._site)
        jacobian = np.vstack([self._jacp[:, :7], self._jacr[:, :7]])
        twist = np.concatenate([translation, rotation])
        q = self.data.qpos[:7]
        free = np.ones(7)
        # Joints that the step would push past a limit are frozen and the step solved again without them.
        for _ in range(4):
            active = jacobian * free
            inverse = active.T @ np.linalg.inv(active @ active.T + self.damping**2 * np.eye(6))
            null_space = np.eye(7) - inverse @ active
            step = inverse @ twist + free * (null_space @ (self.posture_gain * (self._posture - q)))
            blocked = ((q + step < self._low) & (step < 0)) | ((q + step > self._high) & (step > 0))
            if not blocked.any():
                break
            free[blocked] = 0.0
        return self._action(step, grip)

    # --- stages: each returns (action, done) ------------------------------------------------------------------------

    def _to_microwave(self) -> tuple[np.ndarray, bool]:
        self._posture = MICROWAVE_READY
        return self._joint_move(MICROWAVE_READY, tolerance=0.1)

    def _before_handle(self) -> tuple[np.ndarray, bool]:
        target, grasp = self._before_handle_target(), self._handle_grasp()
        return self._reach(target, grasp, grip=1.0), self._near(target, 0.02, grasp)

    def _onto_handle(self) -> tuple[np.ndarray, bool]:
        target = self.data.site_xpos[self._handle].copy()
        return self._reach(target, self._handle_grasp(), grip=1.0, max_step=0.02), self._near(target, 0.008)

    def _grasp_handle(self) -> tuple[np.ndarray, bool]:
        target = self.data.site_xpos[self._handle].copy()
        return self._reach(target, self._handle_grasp(), grip=-1.0), self._stage_steps >= 4

    def _pull_door(self) -> tuple[np.ndarray, bool]:
        hinge = self.data.xpos[self._door]
        turn = _rotation_z(-0.15)
        target = hinge + turn @ (self.data.site_xpos[self._handle] - hinge)
        # Slowly: the faster the pull, the more the bar creeps out of the fingers.
        action = self._reach(target, turn @ self._handle_grasp(), grip=-1.0, max_step=0.02)
        return action, self.data.qpos[self._door_qpos] < self.door_open_angle

    def _release_handle(self) -> tuple[np.ndarray, bool]:
        return self._reach(self._position, self._orientation, grip=1.0), self._stage_steps >= 3

    def _back_off_handle(self) -> tuple[np.ndarray, bool]:
        target = self._before_handle_target()
        return self._reach(target, self._orientation, grip=1.0), self._near(target, 0.03)

    def _to_transit(self) -> tuple[np.ndarray, bool]:
        # Only passed through: a loose tolerance.
        return self._joint_move(TRANSIT, tolerance=0.25)

    def _to_knob(self) -> tuple[np.ndarray, bool]:
        self._posture = KNOB_READY
        return self._joint_move(KNOB_READY, tolerance=0.1)

    def _before_knob(self) -> tuple[np.ndarray, bool]:
        target = self._knob_target(0.1)
        return self._reach(target, KNOB_GRASP, grip=1.0), self._near(target, 0.015, KNOB_GRASP)

    def _onto_knob(self) -> tuple[np.ndarray, bool]:
        target = self._knob_target(self.knob_grasp_depth)
        return self._reach(target, KNOB_GRASP, grip=1.0, max_step=0.015), self._near(target, 0.006)

    def _grasp_knob(self) -> tuple[np.ndarray, bool]:
        return self._reach(self._knob_target(self.knob_grasp_depth), KNOB_GRASP, grip=-1.0), self._stage_steps >= 4

    def _turn_knob(self) -> tuple[np.ndarray, bool]:
        # The knob turns about the world's y axis (its joint axis is -y, its angle negative): lead the gripper's
        # current angle about y. Leading the knob's angle instead stalls, as the knob lags the fingers.
        relative = self._orientation @ KNOB_GRASP.T
        angle = float(np.arctan2(relative[0, 2], relative[0, 0]))
        orientation = _rotation_y(angle + 0.15) @ KNOB_GRASP
        action = self._reach(self._knob_target(self.knob_grasp_depth), orientation, grip=-1.0)
        return action, self.data.qpos[self._knob_qpos] < self.knob_on_angle

    def _release_knob(self) -> tuple[np.ndarray, bool]:
        return self._reach(self._position, self._orientation, grip=1.0), self._stage_steps >= 3

    def _back_off_knob(self) -> tuple[np.ndarray, bool]:
        return self._reach(self._knob_target(0.12), self._orientation, grip=1.0), False


def _orientation_error(current: np.ndarray, desired: np.ndarray) -> np.ndarray:
    """Rotation (axis times sine of the angle, in the world frame) that takes ``current`` to ``desired``."""
    return 0.5 * np.cross(current, desired, axis=0).sum(axis=1)


def _clip_norm(vector: np.ndarray, limit: float) -> np.ndarray:
    norm = float(np.linalg.norm(vector))
    return np.asarray(vector * min(1.0, limit / max(norm, 1e-12)))


# ------------------------------------------------------------------------------------------------------------------
# Registration
# ------------------------------------------------------------------------------------------------------------------

EXPERTS: dict[str, Any] = {ENV_ID: FrankaKitchenMicrowaveBurnerExpert}


def register_kitchen_envs() -> None:
    """Register the kitchen env ids (idempotent)."""
    if ENV_ID not in gym.registry:
        gym.register(
            id=ENV_ID, entry_point="sb3_dipper.envs.kitchen:FrankaKitchenOrderedEnv", max_episode_steps=MAX_EPISODE_STEPS
        )
