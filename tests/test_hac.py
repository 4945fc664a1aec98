"""HAC: the three relabelling rules by hand, clipped targets, the paper_compat switch and a learning check (its runs,
saving and seeding: tests/test_run.py, tests/test_save_load.py)."""

from collections import deque

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import Logger, configure

from sb3_dipper.common.low_level import clipped_soft_target
from sb3_dipper.hac import HAC
from sb3_dipper.hac.hindsight import (
    future_goal_pairs,
    goal_rewards,
    hac_goal_indices,
    hac_goal_pairs,
    hindsight_actions,
    penalized_subgoals,
    penalty_transitions,
    relabel_goals,
)
from tests.conftest import short_maze
from tests.test_save_load import rollout_actions

TINY_HAC = dict(
    option_steps=5,
    learning_starts=40,
    buffer_size=2000,
    batch_size=16,
    low_policy_kwargs=dict(net_arch=[16]),
    seed=0,
    high_batch_size=16,
    high_buffer_size=1000,
    policy_kwargs=dict(net_arch=[16]),
)


def tiny_hac(env, **overrides) -> HAC:
    return HAC("MultiInputPolicy", env, **{**TINY_HAC, **overrides})


def within(radius: float):
    """A vectorised goal test: reached when the Euclidean distance is at most ``radius``."""
    return lambda achieved, desired: np.linalg.norm(achieved - desired, axis=-1) <= radius


# ---------------------------------------------------------------------------------------------------- the rules by hand


def test_hindsight_action_keeps_a_reached_subgoal_and_replaces_a_missed_one():
    proposed = np.array([[0.5, 0.5], [-1.0, 0.0]])
    achieved = np.array([[0.49, 0.52], [0.2, -0.4]])
    actions = hindsight_actions(proposed, achieved, np.array([True, False]))
    np.testing.assert_allclose(actions, [[0.5, 0.5], [0.2, -0.4]])


def test_goal_reward_is_minus_one_until_reached_and_a_reached_goal_ends_bootstrapping():
    rewards, dones = goal_rewards(np.array([[0.0, 0.0], [1.0, 1.0]]), np.array([[0.0, 0.3], [3.0, 1.0]]), within(0.45))
    assert rewards.tolist() == [0.0, -1.0] and dones.tolist() == [1.0, 0.0]


def test_hindsight_goals_relabel_every_transition_of_the_window_with_each_chosen_goal():
    # A window of three options ending at x = 0, 1, 1.2 (y = 0); goals: the last achieved one and the first.
    next_achieved = np.array([[0.0, 0.0], [1.0, 0.0], [1.2, 0.0]])
    transitions, goal_indices = hac_goal_pairs(3, np.array([0, 2]))
    assert transitions.tolist() == [0, 1, 2, 0, 1, 2] and goal_indices.tolist() == [0, 0, 0, 2, 2, 2]
    goals, rewards, dones = relabel_goals(next_achieved, transitions, goal_indices, within(0.45))
    np.testing.assert_allclose(goals, [[0, 0]] * 3 + [[1.2, 0]] * 3)
    # Goal (0, 0): only option 0 ends there. Goal (1.2, 0): options 1 (0.2 away) and 2 end within 0.45 of it.
    assert rewards.tolist() == [0.0, -1.0, -1.0, -1.0, 0.0, 0.0]
    assert dones.tolist() == [1.0, 0.0, 0.0, 0.0, 1.0, 1.0]


def test_hac_goal_choice_always_has_the_last_achieved_goal_and_at_most_one_per_transition():
    rng = np.random.default_rng(0)
    for _ in range(20):
        indices = hac_goal_indices(6, 3, rng)
        assert len(indices) == 3 and indices[-1] == 5 and np.all((indices >= 0) & (indices < 6))
    assert hac_goal_indices(2, 3, rng).tolist()[-1] == 1 and len(hac_goal_indices(2, 3, rng)) == 2
    assert len(hac_goal_indices(4, 0, rng)) == 0


def test_future_goals_of_the_authors_variant_never_come_from_the_past():
    transitions, goals = future_goal_pairs(5, 4, np.random.default_rng(0))
    assert transitions.tolist() == np.repeat(np.arange(5), 4).tolist()
    assert np.all(goals >= transitions) and np.all(goals < 5)


def test_subgoal_testing_penalises_only_tested_missed_subgoals_that_used_all_k_steps():
    tested = np.array([True, True, True, False])
    reached = np.array([False, True, False, False])
    completed = np.array([True, True, False, True])
    assert penalized_subgoals(tested, reached, completed).tolist() == [True, False, False, False]
    rewards, dones = penalty_transitions(2, 15)
    assert rewards.tolist() == [-15.0, -15.0] and dones.tolist() == [1.0, 1.0]


def test_clipped_soft_target_by_hand():
    rewards = th.tensor([[-1.0], [-1.0], [0.0], [-5.0]])
    dones = th.tensor([[0.0], [0.0], [0.0], [1.0]])
    next_q = th.tensor([[-2.0], [-10.0], [0.5], [100.0]])
    next_log_prob = th.full((4, 1), -2.0)
    target = clipped_soft_target(rewards, dones, next_q, next_log_prob, 0.1, 0.9, (-5.0, 0.0))
    # -1 + 0.9 (-2 + 0.2) = -2.62; -1 + 0.9 (-10 + 0.2) = -9.82 -> -5; 0 + 0.9 (0.5 + 0.2) = 0.63 -> 0; no bootstrap: -5.
    assert target.squeeze(1).tolist() == pytest.approx([-2.62, -5.0, 0.0, -5.0], abs=1e-6)


# ---------------------------------------------------------------------------------------------------- the mechanism


def hand_option(model: HAC, tested: list[bool], dones: list[bool], option_steps: int = 5) -> None:
    """Store one hand-made option of two envs (maze: subgoal box [-3.5, 3.5]^2, threshold 0.45, goal radius 0.45).

    Env 0 proposes u = (0.5, 0.5), subgoal (1.75, 1.75), and ends at (1.75, 1.8): reached; its goal (3, 3) is not.
    Env 1 proposes u = (-1, 0), subgoal (-3.5, 0), and ends at (0.7, -1.4), unit (0.2, -0.4): missed; it is 0.3 from
    its goal (1, -1.4), so the goal is reached.
    """
    goals = np.array([[3.0, 3.0], [1.0, -1.4]])
    start = {"observation": np.zeros((2, 4)), "achieved_goal": np.zeros((2, 2)), "desired_goal": goals}
    reached = np.array([[1.75, 1.8], [0.7, -1.4]])
    end = {"observation": np.concatenate([reached, np.zeros((2, 2))], axis=1), "achieved_goal": reached, "desired_goal": goals}
    model.option_env.reached_obs = end
    model.low_level.greedy = np.array(tested)
    infos = [{"achieved_subgoal": reached[env], "option_steps": option_steps} for env in range(2)]
    high_actions = np.array([[0.5, 0.5], [-1.0, 0.0]], dtype=np.float32)
    model._store_option(start, high_actions, end, np.zeros(2), np.array(dones), infos)


def stored(model: HAC) -> dict[str, np.ndarray]:
    buffer = model.higher.replay_buffer
    rows = slice(0, buffer.pos)
    return {
        "actions": buffer.actions[rows, 0],
        "rewards": buffer.rewards[rows, 0],
        "dones": buffer.dones[rows, 0],
        "goals": buffer.observations["desired_goal"][rows, 0],
        "next_achieved": buffer.next_observations["achieved_goal"][rows, 0],
    }


@pytest.fixture
def two_env_model():
    model = tiny_hac(short_maze(n_envs=2))
    model._option_metrics = {"tested_subgoal_missed": deque()}
    return model


def test_an_option_stores_hindsight_actions_and_the_penalty_of_a_missed_tested_subgoal(two_env_model):
    model = two_env_model
    hand_option(model, tested=[True, True], dones=[False, False])
    rows = stored(model)
    # The penalty (env 1's original subgoal, -T = -20 / 5 = -4, no bootstrap), then a hindsight action transition per env.
    np.testing.assert_allclose(rows["actions"], [[-1.0, 0.0], [0.5, 0.5], [0.2, -0.4]], atol=1e-6)
    assert rows["rewards"].tolist() == [-4.0, -1.0, 0.0]
    assert rows["dones"].tolist() == [1.0, 0.0, 1.0]
    np.testing.assert_allclose(rows["goals"], [[1.0, -1.4], [3.0, 3.0], [1.0, -1.4]], atol=1e-6)
    assert list(model._option_metrics["tested_subgoal_missed"]) == [0.0, 1.0]


@pytest.mark.parametrize(
    "tested, option_steps",
    [([False, False], 5), ([True, True], 4)],  # not tested; tested but cut short by the end of the episode
)
def test_no_penalty_without_a_test_or_when_the_option_was_cut_short(tested, option_steps, two_env_model):
    hand_option(two_env_model, tested=tested, dones=[False, False], option_steps=option_steps)
    rows = stored(two_env_model)
    assert rows["rewards"].tolist() == [-1.0, 0.0] and rows["dones"].tolist() == [0.0, 1.0]


def test_the_episode_end_adds_hindsight_goal_transitions_of_the_whole_window():
    model = tiny_hac(short_maze(n_envs=2), n_hindsight_goals=1)
    model._option_metrics = {"tested_subgoal_missed": deque()}
    hand_option(model, tested=[False, False], dones=[False, False])
    hand_option(model, tested=[False, False], dones=[True, True])
    rows = stored(model)
    # 2 options x 2 envs of hindsight actions, then per env its window of 2 options relabelled with its last achieved
    # goal (n_hindsight_goals=1): both options ended there, so both are reached (reward 0, done).
    relabelled = slice(4, 8)
    assert model.higher.replay_buffer.pos == 8
    np.testing.assert_allclose(rows["goals"][relabelled], [[1.75, 1.8]] * 2 + [[0.7, -1.4]] * 2, atol=1e-6)
    np.testing.assert_allclose(rows["actions"][relabelled], [[0.5, 0.5]] * 2 + [[0.2, -0.4]] * 2, atol=1e-6)
    assert rows["rewards"][relabelled].tolist() == [0.0] * 4 and rows["dones"][relabelled].tolist() == [1.0] * 4
    assert model._windows.open_envs() == []


def test_targets_are_clipped_to_minus_t_and_zero_in_training(two_env_model):
    model = two_env_model
    assert model.higher.target_q_bounds == (-4.0, 0.0)  # T = 20 / 5
    sac = model.higher
    sac.set_logger(Logger(None, []))
    for reward, done, expected in ((-100.0, 0.0, -4.0), (10.0, 0.0, 0.0), (-5.0, 1.0, -4.0)):
        sac.replay_buffer.reset()
        obs = {"observation": np.zeros((1, 4)), "achieved_goal": np.zeros((1, 2)), "desired_goal": np.ones((1, 2))}
        for _ in range(16):
            sac.replay_buffer.add(obs, obs, np.zeros((1, 2)), np.array([reward]), np.array([done]), [{}])
        sac.train(gradient_steps=1, batch_size=16)
        assert sac.logger.name_to_value["train/target_q"] == pytest.approx(expected, abs=1e-6)


@pytest.mark.parametrize(
    "max_episode_steps, option_steps, high_steps",
    [(200, 20, 10), (20, 2, 10)],  # the zoo's PointMazeFourRooms-v0 (K = 20 > T = 10), and K = 2 < T = 10
)
def test_the_higher_levels_penalty_and_critic_bound_use_its_horizon_t_not_k(max_episode_steps, option_steps, high_steps):
    """HAC sizes a level's penalty and critic bound by that level's own horizon (``layer.py``, ``critic.py``)."""
    maze = make_vec_env("sb3_dipper:PointMazeFourRooms-v0", n_envs=2, env_kwargs={"max_episode_steps": max_episode_steps})
    model = tiny_hac(maze, option_steps=option_steps)
    model._option_metrics = {"tested_subgoal_missed": deque()}
    assert model.high_steps == high_steps and model.higher.target_q_bounds == (-high_steps, 0.0)
    hand_option(model, tested=[True, True], dones=[False, False], option_steps=option_steps)
    rows = stored(model)
    assert rows["rewards"][0] == -high_steps and rows["dones"][0] == 1.0


# ---------------------------------------------------------------------------------------------------- paper_compat


def test_paper_compat_stores_the_authors_three_episodes_without_penalty_or_termination():
    model = tiny_hac(short_maze(n_envs=2), paper_compat=True)
    assert model.higher.target_q_bounds == pytest.approx((-20.0, 0.0))  # -1 / (1 - 0.95)
    assert model.n_hindsight_goals == 4 and model.high_steps == 4
    model._option_metrics = {"tested_subgoal_missed": deque()}
    # Env 1 runs a greedy episode: its proposed subgoal is stored once more with -T = -4, reached or not.
    hand_option(model, tested=[False, True], dones=[False, False])
    rows = stored(model)
    # Rows: env 1's -T copy; the plain episode (proposed subgoals); the hindsight-action one (reached subgoals, always:
    # (1.75, 1.8) is (0.5, 0.514286) in unit coordinates). Rewards are the env's at the option's end.
    np.testing.assert_allclose(
        rows["actions"], [[-1.0, 0.0], [0.5, 0.5], [-1.0, 0.0], [0.5, 0.514286], [0.2, -0.4]], atol=1e-5
    )
    assert rows["rewards"].tolist() == [-4.0, -1.0, 0.0, -1.0, 0.0]
    assert rows["dones"].tolist() == [0.0] * 5
    assert list(model._option_metrics["tested_subgoal_missed"]) == []


def test_paper_compat_greedy_episodes_come_every_third_episode_after_learning_starts():
    model = tiny_hac(short_maze(n_envs=2), paper_compat=True, learning_starts=0)
    model._episode_counts = np.array([3, 4])
    assert model._greedy_options().tolist() == [True, False]
    model._episode_counts = np.array([5, 6])
    assert model._greedy_options().tolist() == [False, True]


# ---------------------------------------------------------------------------------------------------- runs and saving


@pytest.mark.parametrize("paper_compat", [False, True])
def test_paper_compat_and_the_critic_bounds_survive_save_load(paper_compat, tmp_path):
    model = tiny_hac(short_maze(n_envs=2), paper_compat=paper_compat)
    model.save(tmp_path / "model")
    loaded = HAC.load(tmp_path / "model", env=None)
    assert loaded.paper_compat == paper_compat and loaded.higher.target_q_bounds == model.higher.target_q_bounds


def test_paper_compat_learns_without_subgoal_tests_then_reloads(tmp_path):
    model = tiny_hac(short_maze(n_envs=2), paper_compat=True)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(200, log_interval=1, progress_bar=True)
    assert model.num_timesteps == 200 and model.higher.replay_buffer.size() > 0
    header = set(open(tmp_path / "progress.csv").readline().strip().split(","))
    assert {"train/high_critic_loss", "train/high_target_q", "train/low_actor_loss", "rollout/success_rate"} <= header
    assert "rollout/tested_subgoal_missed" not in header  # logged by default (tests/test_run.py)

    model.save(tmp_path / "model")
    loaded = HAC.load(tmp_path / "model", env=None)
    np.testing.assert_array_equal(rollout_actions(model, short_maze(seed=4)), rollout_actions(loaded, short_maze(seed=4)))


# ---------------------------------------------------------------------------------------------------- learning


def subgoal_distance_from_option_start(model: HAC, env_kwargs: dict, n_episodes: int = 10) -> float:
    """Mean distance from where an option starts to the deterministic subgoal proposed there (held-out episodes)."""
    env = make_vec_env("sb3_dipper:PointMazeFourRooms-v0", n_envs=1, seed=100, env_kwargs=env_kwargs)
    obs, state, episode_start, distances, episodes = env.reset(), None, np.ones(1, dtype=bool), [], 0
    while episodes < n_episodes:
        action, state = model.predict(obs, state=state, episode_start=episode_start, deterministic=True)
        if state[1][0] == model.option_steps - 1:  # a new option: state holds its subgoal
            distances.append(np.linalg.norm(state[0][0] - obs["achieved_goal"][0]))
        obs, _, episode_start, _ = env.step(action)
        episodes += int(episode_start[0])
    env.close()
    return float(np.mean(distances))


def test_subgoal_testing_and_hindsight_actions_pull_subgoals_within_reach():
    """1,500 steps on the maze (goal in the start room): the proposed subgoals come within reach of the option's start,
    as HAC's hindsight actions and subgoal penalties teach (an option moves the ball about one cell, 1 m). Measured over
    seeds 1-3 (K = 10, T = 4): 0.95-1.12 m after training against 2.76-4.01 m untrained (ratios 0.41, 0.24, 0.31); with
    hindsight actions and subgoal testing switched off the ratio stayed at 1.13 (seed 1) and 0.77 (seed 2) (measured
    when the higher level's bound was still [-K, 0])."""
    maze = dict(max_episode_steps=40, start_room="bottom_left", goal_room="bottom_left")
    model = HAC(
        "MultiInputPolicy",
        make_vec_env("sb3_dipper:PointMazeFourRooms-v0", n_envs=2, seed=1, env_kwargs=maze),
        option_steps=10,
        learning_starts=400,
        buffer_size=20_000,
        batch_size=64,
        train_freq=4,
        low_policy_kwargs=dict(net_arch=[64, 64]),
        high_batch_size=64,
        high_gradient_steps=4,
        policy_kwargs=dict(net_arch=[64, 64]),
        seed=1,
    )
    untrained = subgoal_distance_from_option_start(model, maze)
    model.learn(1500)
    trained = subgoal_distance_from_option_start(model, maze)
    assert trained < 0.75 * untrained
