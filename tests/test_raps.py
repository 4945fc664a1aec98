"""RAPS: primitive dispatch by hand for the maze, Fetch and kitchen libraries, K-step primitives, its saved library and
a learning check (its runs, saving and seeding: tests/test_run.py, tests/test_save_load.py)."""

import numpy as np
import pytest
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize

from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.envs.fetch import push_subgoal_space
from sb3_dipper.raps import RAPS
from sb3_dipper.raps.primitives import (
    FRANKA_JOINT_HIGH,
    FRANKA_JOINT_LOW,
    dispatch_primitives,
    primitive_library,
    select_primitive,
)
from tests.conftest import short_maze

TINY_RAPS = dict(
    option_steps=5,
    learning_starts=40,
    seed=0,
    high_batch_size=16,
    high_buffer_size=1000,
    policy_kwargs=dict(net_arch=[16]),
)


def tiny_raps(env, **overrides) -> RAPS:
    return RAPS("MultiInputPolicy", env, **{**TINY_RAPS, **overrides})


MAZE_SPACE = SubgoalSpace(np.full(2, -3.5), np.full(2, 3.5), threshold=0.45)


# ---------------------------------------------------------------------------------------------------- dispatch by hand


def test_the_selector_cuts_minus_one_to_one_into_equal_bins_in_library_order():
    selectors = np.array([-1.0, -0.34, -0.33, 0.0, 0.33, 0.34, 1.0, 7.0])
    assert select_primitive(selectors, 3).tolist() == [0, 0, 1, 1, 1, 2, 2, 2]
    assert select_primitive(selectors, 1).tolist() == [0] * 8


def test_fetch_selector_picks_close_reach_open_and_reach_is_proportional_to_the_gripper_offset():
    library = primitive_library("FetchPush-v4", push_subgoal_space(), spaces.Box(-1.0, 1.0, shape=(4,)))
    assert library.names == ["close_gripper", "reach", "open_gripper"]
    assert primitive_library("FetchPickAndPlaceFixed-v0", push_subgoal_space(), spaces.Box(-1.0, 1.0, shape=(4,))).names == [
        "close_gripper",
        "reach",
        "open_gripper",
    ]
    # Gripper at (1.3, 0.75, 0.45) (the observation's first entries), the rest of the observation irrelevant.
    observation = np.tile(np.array([1.3, 0.75, 0.45, 9.0, 9.0]), (4, 1))
    parameters = np.array(
        [
            [1.4, 0.75, 0.45, -0.9],  # close: arm still, fingers -1
            [1.35, 0.70, 0.50, 0.0],  # reach: 6 * (0.05, -0.05, 0.05), fingers held
            [1.6, 0.75, 0.40, 0.2],  # reach: 6 * (0.3, 0, -0.05) = (1.8, 0, -0.3), clipped to (1, 0, -0.3)
            [1.4, 0.75, 0.45, 0.9],  # open: arm still, fingers +1
        ]
    )
    expected = [[0, 0, 0, -1], [0.3, -0.3, 0.3, 0], [1.0, 0, -0.3, 0], [0, 0, 0, 1]]
    np.testing.assert_allclose(dispatch_primitives(library, observation, parameters), expected, atol=1e-6)


def test_maze_reach_is_the_pd_force_toward_its_target():
    library = primitive_library("PointMazeFourRooms-v0", MAZE_SPACE, spaces.Box(-1.0, 1.0, shape=(2,)))
    assert library.names == ["reach"]
    # Position (0, 0), velocity (0.4, -0.4), target (0.2, -0.1): 2 (0.2, -0.1) - 0.25 (0.4, -0.4) = (0.3, -0.1).
    # Far target (3, 0): 2 * 3 - 0.25 * 0.4 = 5.9, clipped to 1. The selector is ignored with a single primitive.
    observation = np.array([[0.0, 0.0, 0.4, -0.4], [0.0, 0.0, 0.4, -0.4]])
    parameters = np.array([[0.2, -0.1, -1.0], [3.0, 0.0, 1.0]])
    np.testing.assert_allclose(dispatch_primitives(library, observation, parameters), [[0.3, -0.1], [1.0, 0.1]], atol=1e-6)


def test_kitchen_joint_target_is_proportional_to_the_joint_error():
    library = primitive_library("FrankaKitchenMicrowaveBurner-v0", MAZE_SPACE, spaces.Box(-1.0, 1.0, shape=(9,)))
    assert library.names == ["joint_target"] and not library.positional
    np.testing.assert_array_equal(library.argument_low, FRANKA_JOINT_LOW)
    np.testing.assert_array_equal(library.argument_high, FRANKA_JOINT_HIGH)
    observation = np.concatenate([np.zeros((1, 9)), np.full((1, 50), 9.0)], axis=1)  # joints at 0, the rest irrelevant
    targets = np.array([[0.1, -0.1, 0.3, -1.0, 0.0, 0.02, 0.0, 0.04, 0.0, 0.5]])  # + selector
    expected = [[0.5, -0.5, 1.0, -1.0, 0.0, 0.1, 0.0, 0.2, 0.0]]  # 5 * error, clipped to [-1, 1]
    np.testing.assert_allclose(dispatch_primitives(library, observation, targets), expected, atol=1e-6)


def test_unknown_envs_reach_with_the_first_action_entries_and_refuse_too_small_actions():
    library = primitive_library("SomeGoalEnv-v0", MAZE_SPACE, spaces.Box(-1.0, 1.0, shape=(3,)))
    assert library.names == ["reach"]
    action = dispatch_primitives(library, np.array([[0.0, 1.0, 5.0]]), np.array([[0.1, 0.9, 0.0]]))
    np.testing.assert_allclose(action, [[0.6, -0.6, 0.0]], atol=1e-6)
    with pytest.raises(ValueError, match="Register a primitive library"):
        primitive_library("SomeGoalEnv-v0", MAZE_SPACE, spaces.Box(-1.0, 1.0, shape=(1,)))


def test_higher_actions_become_world_arguments_and_the_selector_stays_in_unit_range(maze_env):
    model = tiny_raps(maze_env)
    np.testing.assert_allclose(model.subgoal_space.to_world(np.array([[0.5, -1.0, 0.3]])), [[1.75, -3.5, 0.3]], atol=1e-6)
    # predict: the recurrent state carries the option's arguments; the action is the primitive's for this observation.
    obs = maze_env.reset()
    state = (np.array([[1.0, 0.5, 0.0]], dtype=np.float32), np.array([3]))
    action, next_state = model.predict(obs, state=state, deterministic=True)
    position, velocity = obs["observation"][:, :2], obs["observation"][:, 2:4]
    np.testing.assert_allclose(action, np.clip(2.0 * ([[1.0, 0.5]] - position) - 0.25 * velocity, -1, 1), atol=1e-6)
    assert next_state[1].tolist() == [2]


# ---------------------------------------------------------------------------------------------------- K-step primitives


def test_each_primitive_runs_exactly_option_steps_closed_loop_steps():
    env = short_maze(n_envs=2)
    model = tiny_raps(env, option_steps=5)
    calls: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    scripted = model.option_env.low_level

    class Recorder:
        def act(self, low_obs, deterministic):
            actions = scripted.act(low_obs, deterministic)
            calls.append((low_obs["observation"].copy(), low_obs["desired_goal"].copy(), actions))
            return actions

        def value(self, low_obs):
            return scripted.value(low_obs)

    model.option_env.low_level = Recorder()
    model.option_env.sink = None  # no learner: the option layer runs on its own
    model.option_env.reset()
    _, _, _, infos = model.option_env.step(np.array([[0.5, -0.5, 0.0], [-0.2, 0.8, 1.0]]))
    assert len(calls) == 5 and [info["option_steps"] for info in infos] == [5, 5]
    for observation, arguments, actions in calls:
        np.testing.assert_allclose(arguments, [[1.75, -1.75, 0.0], [-0.7, 2.8, 1.0]], atol=1e-6)
        expected = np.clip(2.0 * (arguments[:, :2] - observation[:, :2]) - 0.25 * observation[:, 2:4], -1.0, 1.0)
        np.testing.assert_allclose(actions, expected, atol=1e-6)
    # Closed loop: every step reads a new observation.
    assert not np.allclose(calls[0][0], calls[-1][0])


def test_one_higher_transition_per_option_and_no_lower_learner(maze_env):
    model = tiny_raps(maze_env, learning_starts=1000)
    model.learn(100)
    assert model.num_timesteps == 100 and model.higher.replay_buffer.pos == 20  # 100 steps of 5-step options
    assert model.replay_buffer is model.higher.replay_buffer and model.lower.replay_buffer is None


def test_observation_normalisation_is_refused():
    with pytest.raises(ValueError, match="norm_obs=False"):
        tiny_raps(VecNormalize(short_maze()))


# ---------------------------------------------------------------------------------------------------- saving


def test_a_model_loaded_without_env_keeps_its_primitive_library(tmp_path, maze_env):
    tiny_raps(maze_env).save(tmp_path / "model")
    assert RAPS.load(tmp_path / "model", env=None).primitives.names == ["reach"]


# ---------------------------------------------------------------------------------------------------- learning

NEAR_GOAL_MAZE = dict(max_episode_steps=30, start_room="bottom_left", goal_room="bottom_left")


def success_rate(model: RAPS, n_episodes: int = 20) -> float:
    """Deterministic success at the last step of held-out episodes."""
    env = make_vec_env("sb3_dipper:PointMazeFourRooms-v0", n_envs=1, seed=100, env_kwargs=NEAR_GOAL_MAZE)
    obs, state, episode_start, successes = env.reset(), None, np.ones(1, dtype=bool), []
    while len(successes) < n_episodes:
        action, state = model.predict(obs, state=state, episode_start=episode_start, deterministic=True)
        obs, _, episode_start, infos = env.step(action)
        if episode_start[0]:
            successes.append(infos[0]["is_success"])
    env.close()
    return float(np.mean(successes))


def near_goal_raps(seed: int) -> tuple[float, float]:
    """Success of an untrained and of a 2,000-step RAPS on a goal in the start room (six 5-step reaches)."""
    model = RAPS(
        "MultiInputPolicy",
        make_vec_env("sb3_dipper:PointMazeFourRooms-v0", n_envs=2, seed=seed, env_kwargs=NEAR_GOAL_MAZE),
        learning_rate=3e-3,
        option_steps=5,
        learning_starts=200,
        high_batch_size=32,
        high_gradient_steps=8,
        policy_kwargs=dict(net_arch=[32, 32]),
        seed=seed,
    )
    untrained = success_rate(model)
    model.learn(2000)
    return untrained, success_rate(model)


def test_the_higher_level_learns_where_to_send_the_reach_primitive():
    """2,000 steps: the higher level learns to aim the reach at the goal (measured: success 1.00 / 0.90 / 1.00 for seeds
    1-3, untrained 0.00: the initial target, the maze's centre, lies behind the room's walls)."""
    untrained, trained = near_goal_raps(seed=1)
    assert untrained <= 0.1 and trained >= 0.5
