"""Every algorithm: save -> load(env=None) -> predict, resuming from a checkpoint with its buffers, and reproducible runs
(as SB3's test_save_load.py and test_deterministic.py)."""

import copy

import numpy as np
import pytest
import torch as th

from sb3_dipper import DAC, DIPPER, SACDemo
from tests.conftest import ALL_ALGORITHMS, OPTION_ALGORITHMS, any_tiny_model, short_maze, tiny_model

# The largest replay buffer a model loaded without an env allocates (PREDICT_ONLY_BUFFER_SIZE per env).
PREDICT_ONLY_ROWS = 16


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


def assert_same_state(first, second, name: str = "parameters") -> None:
    """``get_parameters()`` of two models are equal: every network's and optimizer's state, tensor by tensor."""
    if isinstance(first, dict):
        assert first.keys() == second.keys(), name
        for key in first:
            assert_same_state(first[key], second[key], f"{name}[{key!r}]")
    elif isinstance(first, (list, tuple)):
        assert len(first) == len(second), name
        for index, (item, other) in enumerate(zip(first, second, strict=True)):
            assert_same_state(item, other, f"{name}[{index}]")
    elif isinstance(first, th.Tensor):
        assert th.equal(first, second), name
    else:
        assert first == second, name


def replay_buffers(model) -> dict[str, object]:
    """Every replay buffer a model trains from, by owner: its lower and higher SAC's, or its own (DAC)."""
    buffers = {}
    for name in ("lower", "higher", ""):
        owner = getattr(model, name, None) if name else model
        buffer = getattr(owner, "replay_buffer", None)
        if buffer is not None:
            buffers[f"{name}.replay_buffer"] = buffer
    return buffers


def stored_data(model) -> dict[str, np.ndarray]:
    """What a model collected: each replay buffer's observations and actions, its stored episodes, its labelled pairs."""
    data = {}
    for name, buffer in replay_buffers(model).items():
        rows = buffer.buffer_size if buffer.full else buffer.pos
        data[f"{name}.observations"] = buffer.observations["observation"][:rows].copy()
        data[f"{name}.actions"] = buffer.actions[:rows].copy()
    trajectories = getattr(model, "trajectory_buffer", None)
    if trajectories is not None:
        data["trajectory_buffer.actions"] = trajectories.actions[: len(trajectories)].copy()
    preferences = getattr(model, "preferences", None)
    if preferences is not None:
        pairs = preferences.all_pairs() if len(preferences) > 0 else None
        data["preferences.actions"] = pairs.actions.copy() if pairs is not None else np.zeros(0)
        data["preferences.labels"] = pairs.labels.copy() if pairs is not None else np.zeros(0)
    return data


def assert_same_data(first: dict[str, np.ndarray], second: dict[str, np.ndarray]) -> None:
    assert first.keys() == second.keys()
    for name in first:
        np.testing.assert_array_equal(first[name], second[name], err_msg=name)


# ---------------------------------------------------------------------------------------------------- save, load


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_save_load_without_env_predicts_the_same_actions(model_class, tmp_path, maze_env):
    model = any_tiny_model(model_class, maze_env)
    model.learn(200)
    model.save(tmp_path / "model")
    loaded = model_class.load(tmp_path / "model", env=None)
    assert loaded.get_env() is None
    # Every network and optimizer state comes back (SAGA's discriminator, PIPER's reward model, DIPPER's snapshot...).
    assert_same_state(model.get_parameters(), loaded.get_parameters())
    # A predict-only load allocates no training data: small replay buffers (DPO-FLAT has none: a small episode store).
    buffers = replay_buffers(loaded)
    if buffers:
        assert all(buffer.buffer_size <= PREDICT_ONLY_ROWS for buffer in buffers.values())
    else:
        assert loaded.trajectory_buffer.capacity == 1
    if getattr(loaded, "absorbing_transitions", None) is not None:  # DAC
        assert len(loaded.absorbing_transitions.observations["observation"]) == 1
    np.testing.assert_array_equal(rollout_actions(model, short_maze(seed=4)), rollout_actions(loaded, short_maze(seed=4)))


def test_the_planning_graph_is_saved_with_the_model(tmp_path, maze_env):
    model = tiny_model(DIPPER, maze_env, planner_kwargs=dict(mode="subgoal", lookahead=2))
    model.learn(400)
    assert len(model.planner.graph) > 0
    model.save(tmp_path / "model")
    loaded = DIPPER.load(tmp_path / "model")
    np.testing.assert_array_equal(loaded.planner.graph.edges, model.planner.graph.edges)
    np.testing.assert_array_equal(rollout_actions(model, short_maze(seed=4)), rollout_actions(loaded, short_maze(seed=4)))


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_a_checkpoint_with_buffers_resumes_where_it_stopped(model_class, tmp_path):
    """Both of SB3's ways to resume: ``load(path, env=env)``, and ``load(path)`` then ``set_env(env)``; each then
    ``load_replay_buffer`` (DIPPER, PIPER and DPO-FLAT also bring back their episodes and labelled pairs)."""
    model = any_tiny_model(model_class, short_maze(n_envs=2))
    model.learn(200)
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    saved_data = stored_data(model)
    assert all(len(data) > 0 for data in saved_data.values())
    # Episodes and labelled pairs (and DAC's absorbing transitions) are npz files, read without pickle.
    assert any(tmp_path.glob("buffer*.npz")) or not hasattr(model, "preferences")
    for path in tmp_path.glob("buffer*.npz"):
        with np.load(path, allow_pickle=False) as data:
            assert data.files

    loaded_with_env = model_class.load(tmp_path / "model", env=short_maze(n_envs=2, seed=1))
    given_env_later = model_class.load(tmp_path / "model")
    given_env_later.set_env(short_maze(n_envs=2, seed=1))
    for resumed in (loaded_with_env, given_env_later):
        resumed.load_replay_buffer(tmp_path / "buffer.pkl")
        assert_same_data(stored_data(resumed), saved_data)
        # Training buffers of the configured size (the predict-only load's small ones are gone).
        assert {name: buffer.buffer_size for name, buffer in replay_buffers(resumed).items()} == {
            name: buffer.buffer_size for name, buffer in replay_buffers(model).items()
        }
        resumed.learn(100, reset_num_timesteps=False)
        assert resumed.num_timesteps == 300


# ---------------------------------------------------------------------------------------------------- determinism


@pytest.mark.parametrize("model_class", [*OPTION_ALGORITHMS, SACDemo, DAC])
def test_a_set_env_that_fails_partway_leaves_a_loaded_model_as_it_was(model_class, tmp_path, monkeypatch):
    """A model loaded without an env is rebuilt for the env set_env gives it; a failure inside the rebuild (after fresh
    networks were made) must leave the trained networks, the env and the predictions as they were."""
    model = any_tiny_model(model_class, short_maze(n_envs=2))
    model.learn(100)
    model.save(tmp_path / "model")
    loaded = model_class.load(tmp_path / "model")
    parameters = copy.deepcopy(loaded.get_parameters())
    actions = rollout_actions(loaded, short_maze(seed=4))
    rebuild = model_class._setup_model

    def rebuild_then_fail(self):
        rebuild(self)
        raise RuntimeError("refused after the rebuild")

    monkeypatch.setattr(model_class, "_setup_model", rebuild_then_fail)
    with pytest.raises(RuntimeError, match="refused after the rebuild"):
        loaded.set_env(short_maze(n_envs=2, seed=1))
    monkeypatch.undo()
    assert loaded.env is None
    assert_same_state(loaded.get_parameters(), parameters)
    np.testing.assert_array_equal(rollout_actions(loaded, short_maze(seed=4)), actions)
    loaded.set_env(short_maze(n_envs=2, seed=1))  # and the env can still be given
    loaded.learn(50, reset_num_timesteps=False)


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_same_seed_same_first_five_hundred_steps(model_class):
    """Both levels' weights and optimizers, and everything collected, over 500 steps of 20-step episodes (every
    network of every algorithm is updated by then)."""
    runs = []
    for _ in range(2):
        model = any_tiny_model(model_class, short_maze(seed=2), seed=11, learning_starts=100)
        model.learn(500)
        runs.append((model.get_parameters(), stored_data(model)))
    (parameters_a, data_a), (parameters_b, data_b) = runs
    assert_same_data(data_a, data_b)
    assert_same_state(parameters_a, parameters_b)


# What the ``dipper`` profiles of the paper's tasks turn on beyond the paper: progress labels, goal episodes, executed
# subgoals, a planner steering training only, a goal-anchored policy with a floor on its log-std, the anchor's leash;
# and pairs matched to the control and cut to option segments (candidates), whose draws come from the same seeded stream.
PROFILE_SETTINGS = dict(
    preference_source="progress",
    segment_options=2,
    switch_kwargs=dict(
        nll_coef=1.0,
        hindsight_actions=False,
        truncate_at_goal=True,
        goal_episode_prob=0.5,
        anchor_coef=0.1,
        matched_control_prob=0.5,
    ),
    planner_kwargs=dict(mode="subgoal", lookahead=2, in_predict=False),
    policy_kwargs=dict(net_arch=[16], acting_tau=0.05, log_std_min=-2.0, goal_anchored=True),
)


def test_dippers_profile_settings_give_the_same_run_and_resume_from_a_checkpoint(tmp_path):
    """The profiles' switches draw their randomness (goal episodes, planner, tie-breaks) from the seeded streams, and
    a checkpoint of such a model loads without an env, predicts as saved and trains on with its buffers."""
    runs = []
    for _ in range(2):
        model = tiny_model(DIPPER, short_maze(n_envs=2, seed=2), seed=11, learning_starts=100, **PROFILE_SETTINGS)
        model.learn(600)
        runs.append((model.get_parameters(), stored_data(model)))
    (parameters_a, data_a), (parameters_b, data_b) = runs
    assert_same_data(data_a, data_b)
    assert_same_state(parameters_a, parameters_b)
    # The run met what the settings do: goal-driven and policy-driven episodes, labelled pairs, higher-level updates.
    trajectories = model.trajectory_buffer
    assert 0 < trajectories.goal_driven[: len(trajectories)].sum() < len(trajectories)
    assert len(model.preferences) > 0 and model._n_updates > 0

    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    loaded = DIPPER.load(tmp_path / "model")
    assert loaded.switch_kwargs == model.switch_kwargs and not loaded.planner.in_predict
    assert loaded.preference_pipeline.sampler.matched_control_prob == 0.5
    np.testing.assert_array_equal(rollout_actions(model, short_maze(seed=4)), rollout_actions(loaded, short_maze(seed=4)))
    loaded.set_env(short_maze(n_envs=2, seed=3))
    loaded.load_replay_buffer(tmp_path / "buffer.pkl")
    assert_same_data(stored_data(loaded), stored_data(model))
    assert loaded.segment_options == 2 and loaded.preferences.all_pairs().mask.shape[-1] == 2
    loaded.learn(100, reset_num_timesteps=False)
    assert loaded.num_timesteps == 700


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_a_different_seed_gives_a_different_run(model_class):
    first = any_tiny_model(model_class, short_maze(seed=2), seed=1)
    second = any_tiny_model(model_class, short_maze(seed=2), seed=2)
    first.learn(100)
    second.learn(100)
    first_data, second_data = stored_data(first), stored_data(second)
    assert not any(np.array_equal(first_data[name], second_data[name]) for name in first_data if name.endswith("actions"))
    first_parameters, second_parameters = first.policy.state_dict(), second.policy.state_dict()
    assert not all(th.equal(first_parameters[name], second_parameters[name]) for name in first_parameters)
