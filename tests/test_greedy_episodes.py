"""Greedy episodes (``greedy_episode_prob``): the lower level collects some episodes with its deterministic action."""

import numpy as np
import pytest
import torch as th

from sb3_dipper import DIPPER, HIER, PIPER, SAGA
from tests.conftest import short_maze, tiny_model

# The algorithms whose lower level explores by sampling SAC's policy (HAC tests its subgoals instead, RAPS is scripted).
GREEDY_ALGORITHMS = [DIPPER, HIER, PIPER, SAGA]


def stored_transitions(model, start: int) -> tuple[dict[str, th.Tensor], np.ndarray]:
    """The lower buffer's observations and scaled actions from vec step ``start`` on, flattened over envs."""
    buffer = model.lower.replay_buffer
    rows = slice(start, buffer.pos)
    observations = {
        key: th.as_tensor(value[rows].reshape(-1, value.shape[-1]), dtype=th.float32)
        for key, value in buffer.observations.items()
    }
    return observations, buffer.actions[rows].reshape(-1, buffer.actions.shape[-1])


def test_the_lower_level_acts_greedily_in_the_greedy_envs_only():
    model = tiny_model(DIPPER, short_maze(n_envs=3))
    model.learn(60)
    observations, _ = stored_transitions(model, 0)
    low_obs = {key: value[:3].numpy() for key, value in observations.items()}
    low_level = model.low_level
    greedy_actions = low_level.act(low_obs, deterministic=True)

    low_level.greedy = np.array([True, False, True])
    mixed = low_level.act(low_obs, deterministic=False)
    np.testing.assert_allclose(mixed[[0, 2]], greedy_actions[[0, 2]], rtol=1e-6)
    assert not np.allclose(mixed[1], greedy_actions[1]), "the other env samples its action"

    low_level.greedy = None
    assert not np.allclose(low_level.act(low_obs, deterministic=False), greedy_actions)
    np.testing.assert_allclose(low_level.act(low_obs, deterministic=True), greedy_actions, rtol=1e-6)


@pytest.mark.parametrize("model_class", GREEDY_ALGORITHMS)
@pytest.mark.parametrize("greedy_episode_prob", [0.0, 1.0])
def test_greedy_episodes_store_the_lower_levels_deterministic_actions(model_class, greedy_episode_prob):
    # No lower updates: the actor that acted is the actor checked.
    model = tiny_model(model_class, short_maze(n_envs=2), greedy_episode_prob=greedy_episode_prob, gradient_steps=0)
    model.learn(120)
    observations, actions = stored_transitions(model, start=model.learning_starts // 2)  # after the random warm-up
    with th.no_grad():
        deterministic = model.lower.actor(observations, deterministic=True).numpy()
    assert np.allclose(actions, deterministic, atol=1e-5) == (greedy_episode_prob == 1.0)
    assert (model.low_level.greedy is None) == (greedy_episode_prob == 0.0)


def test_greedy_episodes_are_drawn_per_env_when_its_episode_starts(tmp_path):
    model = tiny_model(DIPPER, short_maze(n_envs=4), greedy_episode_prob=0.25)
    model.learn(40)
    before = model.low_level.greedy.copy()
    for _ in range(20):
        model._draw_greedy_episodes(np.array([1, 0, 0, 0]))  # dones as numbers select envs, not indices
        np.testing.assert_array_equal(model.low_level.greedy[1:], before[1:])
    shares = []
    for _ in range(2000):
        model._draw_greedy_episodes(np.ones(4, dtype=bool))
        shares.append(model.low_level.greedy.mean())
    assert abs(np.mean(shares) - 0.25) < 0.03

    model.save(tmp_path / "model.zip")
    assert DIPPER.load(tmp_path / "model.zip").greedy_episode_prob == 0.25


@pytest.mark.parametrize("model_class", GREEDY_ALGORITHMS)
def test_greedy_episode_prob_outside_zero_to_one_is_refused(model_class, maze_env):
    with pytest.raises(ValueError, match="greedy_episode_prob"):
        tiny_model(model_class, maze_env, greedy_episode_prob=1.5)
