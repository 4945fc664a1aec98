"""The four-room PointMaze: a standard SB3 goal env with a long-horizon task."""

import os
import tempfile

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.env_checker import check_env

import sb3_dipper  # noqa: F401  (registers the env ids)
from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.envs.point_maze import (
    FOUR_ROOMS_MAP,
    ROOMS,
    PointMazeExpert,
    PointMazeFourRoomsEnv,
    reach_action,
    shortest_cell_path,
)


@pytest.fixture
def env():
    env = gym.make("PointMazeFourRooms-v0")
    yield env
    env.close()


def cell_of(xy: np.ndarray) -> tuple[int, int]:
    return int(np.floor(4.5 - xy[1])), int(np.floor(xy[0] + 4.5))


def test_passes_sb3_env_checker():
    check_env(PointMazeFourRoomsEnv(), warn=False)


def test_registered_with_a_time_limit(env):
    assert env.spec.max_episode_steps == 200
    obs, _ = env.reset(seed=0)
    assert {key: value.shape for key, value in obs.items()} == {
        "observation": (4,),
        "achieved_goal": (2,),
        "desired_goal": (2,),
    }
    obs, reward, terminated, _, info = env.step(env.action_space.sample())
    assert obs["observation"].shape == (4,) and isinstance(reward, float) and not terminated
    assert set(info) >= {"is_success"}


def test_compute_reward_is_vectorised_and_matches_single_calls(env):
    rng = np.random.default_rng(0)
    achieved, desired = rng.uniform(-3, 3, (64, 2)), rng.uniform(-3, 3, (64, 2))
    desired[:8] = achieved[:8] + 0.1
    batch = env.unwrapped.compute_reward(achieved, desired, {})
    single = [env.unwrapped.compute_reward(a, d, {}) for a, d in zip(achieved, desired, strict=True)]
    np.testing.assert_array_equal(batch, single)
    assert set(np.unique(batch)) <= {-1.0, 0.0} and np.all(batch[:8] == 0.0)


def test_success_is_within_the_threshold_and_matches_the_reward(env):
    obs, _ = env.reset(seed=1)
    for _ in range(20):
        obs, reward, _, _, info = env.step(env.action_space.sample())
        distance = np.linalg.norm(obs["achieved_goal"] - obs["desired_goal"])
        assert info["is_success"] == float(distance <= 0.45) == float(reward == 0.0)


def test_start_and_goal_lie_in_opposite_rooms():
    env = PointMazeFourRoomsEnv()
    for seed in range(30):
        obs, _ = env.reset(seed=seed)
        assert cell_of(obs["achieved_goal"]) in ROOMS["bottom_left"]
        assert cell_of(obs["desired_goal"]) in ROOMS["top_right"]
    other = PointMazeFourRoomsEnv(start_room="top_left", goal_room="bottom_right")
    obs, _ = other.reset(seed=0)
    assert cell_of(obs["achieved_goal"]) in ROOMS["top_left"] and cell_of(obs["desired_goal"]) in ROOMS["bottom_right"]


def test_making_the_env_leaves_no_model_file_behind(tmp_path, monkeypatch):
    """gymnasium-robotics writes the maze's model into the temp folder and leaves it there; the env removes it."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    env = PointMazeFourRoomsEnv()
    assert os.path.dirname(env.tmp_xml_file_path) == str(tmp_path) and list(tmp_path.iterdir()) == []
    env.reset(seed=0)
    env.step(env.action_space.sample())
    env.close()


def test_unknown_room_is_refused():
    with pytest.raises(ValueError, match="Unknown goal_room"):
        PointMazeFourRoomsEnv(goal_room="kitchen")


def test_same_seed_same_episode():
    first, second = PointMazeFourRoomsEnv(), PointMazeFourRoomsEnv()
    actions = np.random.default_rng(0).uniform(-1, 1, (30, 2))
    obs_a, _ = first.reset(seed=7)
    obs_b, _ = second.reset(seed=7)
    for action in actions:
        obs_a, *_ = first.step(action)
        obs_b, *_ = second.step(action)
    for key in obs_a:
        np.testing.assert_array_equal(obs_a[key], obs_b[key])


def test_declares_its_subgoal_space(env):
    space = env.unwrapped.subgoal_space
    assert isinstance(space, SubgoalSpace) and space.dim == 2 and space.threshold == pytest.approx(0.45)
    np.testing.assert_allclose(space.low, [-3.5, -3.5])


def test_rooms_are_connected_only_through_doorways():
    path = shortest_cell_path((6, 2), (2, 6), FOUR_ROOMS_MAP)
    assert len(path) - 1 == 12
    assert (4, 1) in path or (7, 4) in path


def run_controller(controller, seeds: range) -> float:
    env = gym.make("PointMazeFourRooms-v0")
    successes = []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        done = False
        while not done:
            obs, _, terminated, truncated, info = env.step(controller(obs))
            done = terminated or truncated
        successes.append(info["is_success"])
    return float(np.mean(successes))


def test_scripted_expert_solves_the_task():
    expert = PointMazeExpert()
    assert run_controller(expert.act, range(10)) == 1.0


def test_heading_straight_for_the_goal_fails():
    greedy = lambda obs: reach_action(obs["observation"][:2], obs["observation"][2:4], obs["desired_goal"])  # noqa: E731
    assert run_controller(greedy, range(20)) <= 0.1


def test_renders_headless():
    env = gym.make("PointMazeFourRooms-v0", render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    env.close()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.std() > 0
