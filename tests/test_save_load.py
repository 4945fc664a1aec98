"""save -> load(env=None) -> predict, resuming from checkpoints, and reproducible runs."""

import numpy as np
import pytest
import torch as th

from sb3_dipper import DIPPER
from tests.conftest import ALL_ALGORITHMS, HIERARCHICAL_ALGORITHMS, any_tiny_model, short_maze, tiny_model


def rollout_actions(model, env, steps: int = 30) -> np.ndarray:
    """Deterministic primitive actions over ``steps`` steps, carrying the option state as evaluate_policy does."""
    obs = env.reset()
    state, episode_start, actions = None, np.ones(env.num_envs, dtype=bool), []
    for _ in range(steps):
        action, state = model.predict(obs, state=state, episode_start=episode_start, deterministic=True)
        obs, _, dones, _ = env.step(action)
        episode_start = dones
        actions.append(action)
    return np.array(actions)


@pytest.mark.parametrize("model_class", HIERARCHICAL_ALGORITHMS)
def test_save_load_without_env_predicts_the_same_actions(model_class, tmp_path, maze_env):
    model = tiny_model(model_class, maze_env)
    model.learn(200)
    model.save(tmp_path / "model")
    loaded = model_class.load(tmp_path / "model", env=None)
    assert loaded.get_env() is None
    # A predict-only load does not allocate the training buffers.
    assert loaded.lower.replay_buffer.buffer_size < 100
    np.testing.assert_array_equal(rollout_actions(model, short_maze(seed=4)), rollout_actions(loaded, short_maze(seed=4)))


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_every_algorithm_saves_loads_without_env_and_predicts_the_same(model_class, tmp_path, maze_env):
    model = any_tiny_model(model_class, maze_env)
    model.learn(200)
    model.save(tmp_path / "model")
    loaded = model_class.load(tmp_path / "model", env=None)
    assert loaded.get_env() is None
    np.testing.assert_array_equal(rollout_actions(model, short_maze(seed=4)), rollout_actions(loaded, short_maze(seed=4)))


# The hierarchical algorithms repeat their runs in the stronger test_same_seed_same_first_thousand_steps below (both
# levels' weights and the collected observations, over a thousand steps).
@pytest.mark.parametrize("model_class", [model for model in ALL_ALGORITHMS if model not in HIERARCHICAL_ALGORITHMS])
def test_the_other_algorithms_repeat_their_runs_with_the_same_seed(model_class):
    def trained_parameters():
        model = any_tiny_model(model_class, short_maze(seed=3), seed=3)
        model.learn(300)
        return {name: tensor.clone() for name, tensor in model.policy.state_dict().items()}

    first, second = trained_parameters(), trained_parameters()
    assert first.keys() == second.keys()
    assert all(th.equal(first[name], second[name]) for name in first)


def test_the_planning_graph_is_saved_with_the_model(tmp_path, maze_env):
    model = tiny_model(DIPPER, maze_env, planner_kwargs=dict(mode="subgoal", lookahead=2))
    model.learn(400)
    assert len(model.planner.graph) > 0
    model.save(tmp_path / "model")
    loaded = DIPPER.load(tmp_path / "model")
    np.testing.assert_array_equal(loaded.planner.graph.edges, model.planner.graph.edges)
    np.testing.assert_array_equal(rollout_actions(model, short_maze(seed=4)), rollout_actions(loaded, short_maze(seed=4)))


@pytest.mark.parametrize("model_class", HIERARCHICAL_ALGORITHMS)
def test_loaded_model_keeps_training(model_class, tmp_path, maze_env):
    model = tiny_model(model_class, maze_env)
    model.learn(100)
    model.save(tmp_path / "model")
    loaded = model_class.load(tmp_path / "model", env=short_maze(seed=1))
    assert loaded.lower.replay_buffer.buffer_size == 2000
    loaded.learn(100, reset_num_timesteps=False)
    assert loaded.num_timesteps == 200


@pytest.mark.parametrize("model_class", HIERARCHICAL_ALGORITHMS)
def test_checkpoint_with_buffers_resumes_where_it_stopped(model_class, tmp_path, maze_env):
    model = tiny_model(model_class, maze_env)
    model.learn(200)
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    resumed = model_class.load(tmp_path / "model", env=short_maze(seed=1))
    resumed.load_replay_buffer(tmp_path / "buffer.pkl")
    assert resumed.lower.replay_buffer.pos == model.lower.replay_buffer.pos
    np.testing.assert_array_equal(resumed.lower.replay_buffer.actions, model.lower.replay_buffer.actions)
    if model_class is DIPPER:
        assert len(resumed.preferences) == len(model.preferences) > 0
        np.testing.assert_array_equal(resumed.preferences.all_pairs().labels, model.preferences.all_pairs().labels)
        assert len(resumed.trajectory_buffer) == len(model.trajectory_buffer) > 0
        assert list(np.load(tmp_path / "buffer.high.npz", allow_pickle=False).keys())
    else:
        assert resumed.higher.replay_buffer.pos == model.higher.replay_buffer.pos > 0
    resumed.learn(100, reset_num_timesteps=False)
    assert resumed.num_timesteps == 300


def parameters(model) -> dict[str, th.Tensor]:
    return {name: tensor.clone() for name, tensor in model.lower.policy.state_dict().items()} | {
        f"high.{name}": tensor.clone() for name, tensor in model.policy.state_dict().items()
    }


@pytest.mark.parametrize("model_class", HIERARCHICAL_ALGORITHMS)
def test_same_seed_same_first_thousand_steps(model_class):
    runs = []
    for _ in range(2):
        model = tiny_model(model_class, short_maze(seed=2), seed=11, learning_starts=200)
        model.learn(1000)
        runs.append((parameters(model), model.lower.replay_buffer.observations["observation"][:1000].copy()))
    (params_a, observations_a), (params_b, observations_b) = runs
    np.testing.assert_array_equal(observations_a, observations_b)
    assert params_a.keys() == params_b.keys()
    for name in params_a:
        assert th.equal(params_a[name], params_b[name]), name


def test_a_different_seed_gives_a_different_run():
    first = tiny_model(DIPPER, short_maze(seed=2), seed=1)
    second = tiny_model(DIPPER, short_maze(seed=2), seed=2)
    first.learn(100)
    second.learn(100)
    assert not np.array_equal(first.lower.replay_buffer.actions[:50], second.lower.replay_buffer.actions[:50])
