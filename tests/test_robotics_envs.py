"""gymnasium-robotics' own goal envs out of the box: Fetch reach and slide, every PointMaze and AntMaze map."""

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.monitor import Monitor

from sb3_dipper import DIPPER
from sb3_dipper.common.subgoals import registered_subgoal_space, resolve_subgoal_space
from sb3_dipper.envs.robotics import MAZE_GOAL_RADIUS, MAZE_IS_SUCCESS, maze_env_ids
from tests.conftest import tiny_model

UPSTREAM_IDS = ["FetchReach-v4", "FetchSlide-v4", "PointMaze_UMaze-v3", "AntMaze_UMaze-v5"]


@pytest.mark.parametrize("env_id", UPSTREAM_IDS)
def test_dipper_trains_on_an_upstream_goal_env(env_id):
    env = make_vec_env(env_id, n_envs=1, seed=0, env_kwargs={"max_episode_steps": 20})
    model = tiny_model(DIPPER, env).learn(100)
    # SB3 records a success per finished episode only when the env reports `is_success`.
    assert len(model.ep_success_buffer) == 5
    env.close()


def test_every_maze_map_has_a_subgoal_space_and_reports_is_success():
    maze_ids = maze_env_ids()
    for family in ("PointMaze", "AntMaze"):
        # Every map of gymnasium-robotics' maze list, sparse and dense.
        assert len([env_id for env_id in maze_ids if env_id.startswith(f"{family}_")]) >= 20
    for env_id in maze_ids:
        assert registered_subgoal_space(env_id) is not None, env_id
        assert MAZE_IS_SUCCESS in gym.spec(env_id).additional_wrappers, env_id


@pytest.mark.parametrize(
    ("env_id", "half_width", "half_height"), [("PointMaze_UMaze-v3", 1.5, 1.5), ("AntMaze_Medium-v5", 12.0, 12.0)]
)
def test_a_maze_subgoal_box_spans_its_open_cells_and_holds_its_goals(env_id, half_width, half_height):
    env = make_vec_env(env_id, n_envs=1)
    space = resolve_subgoal_space(env)
    np.testing.assert_allclose(space.low, [-half_width, -half_height])
    np.testing.assert_allclose(space.high, [half_width, half_height])
    assert space.threshold == MAZE_GOAL_RADIUS
    assert_goals_inside(env, space)


def assert_goals_inside(env, space) -> None:
    """The achieved and desired goals of ten reset episodes lie in the subgoal box; closes the env."""
    for seed in range(10):
        env.seed(seed)
        obs = env.reset()
        for key in ("achieved_goal", "desired_goal"):
            assert np.all((space.low <= obs[key][0]) & (obs[key][0] <= space.high)), (seed, key, obs[key])
    env.close()


@pytest.mark.parametrize("env_id", ["FetchReach-v4", "FetchSlide-v4"])
def test_a_fetch_subgoal_box_holds_its_goals_and_object_starts(env_id):
    env = make_vec_env(env_id, n_envs=1)
    space = resolve_subgoal_space(env)
    assert space.threshold == 0.05 and space.dim == 3
    assert_goals_inside(env, space)


# AntMaze-v3 reports no info["success"]: the wrapper recomputes it from the goal distance.
@pytest.mark.parametrize("env_id", ["PointMaze_UMaze-v3", "AntMaze_UMaze-v3"])
def test_a_maze_reports_is_success_to_the_monitor(env_id):
    env = Monitor(gym.make(env_id, max_episode_steps=2), info_keywords=("is_success",))
    obs, _ = env.reset(seed=0)
    _, _, _, _, info = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
    assert info["is_success"] == 0.0
    # Put the goal where the agent is: the next step ends the episode at the goal.
    env.unwrapped.goal = obs["achieved_goal"].copy()
    _, _, _, truncated, info = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
    assert truncated and info["is_success"] == 1.0
    assert info["episode"]["is_success"] == 1.0
    env.close()
