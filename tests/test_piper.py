"""PIPER: the Bradley-Terry reward-model loss by hand, rewards replaced by r_phi at sampling, its saved labels and episodes,
PIPER-No-V, a learning check (its runs, saving and seeding: tests/test_run.py, tests/test_save_load.py)."""

import math

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_dipper.common.losses import preference_accuracy
from sb3_dipper.common.preferences import sample_trajectory_pairs
from sb3_dipper.piper import PIPER, LearnedRewardReplayBuffer
from sb3_dipper.piper.piper import bradley_terry_loss, reward_model_logits
from tests.conftest import short_maze

TINY_PIPER = dict(
    option_steps=5,
    learning_starts=40,
    buffer_size=2000,
    batch_size=16,
    low_policy_kwargs=dict(net_arch=[16]),
    seed=0,
    high_batch_size=16,
    high_buffer_size=1000,
    policy_kwargs=dict(net_arch=[16]),
    n_preference_pairs=200,
    reward_batch_size=8,
    trajectory_buffer_size=50,
    reward_model_kwargs=dict(net_arch=[16]),
)


def tiny_piper(env, **overrides) -> PIPER:
    return PIPER("MultiInputPolicy", env, **{**TINY_PIPER, **overrides})


# ---------------------------------------------------------------------------------------------------- the loss by hand

# One pair of three-step trajectories whose last step is padding: R^1 = 0.5 + 0.2 = 0.7, R^2 = 0.1 - 0.3 = -0.2, z = 0.9.
STEP_REWARDS = [[[0.5, 0.2, 0.9]], [[0.1, -0.3, 0.4]]]
MASK = th.tensor([[[True, True, False]], [[True, True, False]]])


@pytest.mark.parametrize(
    "label, expected",
    [
        (1.0, math.log1p(math.exp(-0.9))),  # -log sigma(0.9) = 0.341154
        (0.0, math.log1p(math.exp(0.9))),  # -log sigma(-0.9) = 1.241154
        (0.5, 0.5 * (math.log1p(math.exp(-0.9)) + math.log1p(math.exp(0.9)))),  # a tie: 0.791154
    ],
)
def test_bradley_terry_loss_by_hand(label, expected):
    loss, logits = bradley_terry_loss(th.tensor(STEP_REWARDS), MASK, th.tensor([label]))
    assert logits.item() == pytest.approx(0.9, abs=1e-6)
    assert loss.item() == pytest.approx(expected, abs=1e-6)


def test_bradley_terry_gradient_raises_the_preferred_trajectory_and_ignores_padding():
    step_rewards = th.tensor(STEP_REWARDS, requires_grad=True)
    loss, _ = bradley_terry_loss(step_rewards, MASK, th.tensor([1.0]))
    loss.backward()
    # d loss / d r^1_t = sigma(z) - y = 0.710950 - 1 = -0.289050 on real steps; the opposite for tau^2; 0 on padding.
    expected = th.tensor([[[-0.289050, -0.289050, 0.0]], [[0.289050, 0.289050, 0.0]]])
    assert th.allclose(step_rewards.grad, expected, atol=1e-6)


def test_logits_of_pairs_of_unequal_lengths():
    step_rewards = th.tensor([[[1.0, 1.0], [0.5, -1.0]], [[0.25, 9.0], [0.5, 0.5]]])
    mask = th.tensor([[[True, True], [True, True]], [[True, False], [True, True]]])
    assert reward_model_logits(step_rewards, mask).tolist() == pytest.approx([2.0 - 0.25, -0.5 - 1.0])


# ---------------------------------------------------------------------------------------------------- the mechanism


@pytest.fixture(scope="module")
def trained() -> PIPER:
    """A tiny PIPER (higher-level HER on) after 200 steps; tests below must leave it as they found it."""
    model = tiny_piper(short_maze())
    model.learn(200)
    return model


@pytest.fixture(scope="module")
def trained_without_her() -> PIPER:
    model = tiny_piper(short_maze(), high_her=False)
    model.learn(200)
    return model


class HandReward(th.nn.Module):
    """A stand-in reward model with a value computable by hand: ``g_x + 10 u_x``."""

    def forward(self, obs, actions):
        return obs["desired_goal"][:, 0].float() + 10.0 * actions[:, 0]


@pytest.mark.parametrize("high_her", [True, False])
def test_sampled_rewards_are_the_reward_models_for_the_sampled_goals(high_her, trained, trained_without_her):
    model = trained if high_her else trained_without_her
    buffer = model.higher.replay_buffer
    assert isinstance(buffer, LearnedRewardReplayBuffer) and buffer.her_ratio == pytest.approx(0.8 if high_her else 0.0)
    assert buffer.reward_model is model.reward_model
    samples = buffer.sample(64)
    with th.no_grad():
        expected = model.reward_model(samples.observations, samples.actions)
    np.testing.assert_allclose(samples.rewards.squeeze(-1).numpy(), expected.numpy(), rtol=1e-6)

    buffer.reward_model = HandReward()
    try:
        samples = buffer.sample(64)
    finally:
        buffer.reward_model = model.reward_model
    goals, actions = samples.observations["desired_goal"].numpy(), samples.actions.numpy()
    # The buffer sums in float32 terms of up to about 10: a reward near 0 is off by float32 rounding in absolute terms.
    np.testing.assert_allclose(samples.rewards.squeeze(-1).numpy(), goals[:, 0] + 10.0 * actions[:, 0], rtol=1e-5, atol=1e-5)
    # HER relabels goals (with achieved ones), and their rewards follow the relabelled goal; without HER none changes.
    stored_goals = buffer.observations["desired_goal"][: buffer.pos, 0]
    relabelled = ~np.any(np.all(np.isclose(goals[:, None, :], stored_goals[None]), axis=-1), axis=1)
    assert relabelled.any() == high_her


def test_the_reward_model_is_not_pickled_with_the_buffer(trained):
    assert "reward_model" not in trained.higher.replay_buffer.__getstate__()


def test_the_value_term_breaks_ties_of_the_primitive_in_the_loop_score(trained):
    pairs = sample_trajectory_pairs(trained.trajectory_buffer, 200, 0.0, trained.subgoal_space, np.random.default_rng(0))
    no_value = tiny_piper(short_maze(), value_reg_coef=0.0)
    assert no_value.preference_pipeline.labeler.value_score is None
    ties_without = np.mean(no_value.preference_pipeline.labeler.label(pairs) == 0.5)
    ties_with = np.mean(trained.preference_pipeline.labeler.label(pairs) == 0.5)
    # (The lower value is estimated at a sampled lower action, as in the authors' code, so even a pair of two copies
    # of one trajectory rarely ties.)
    assert ties_with < 0.05 and ties_without > 0.5
    # The term is lambda * sum_t V^L: at lambda = 1e-6 it cannot outweigh one more option at the goal.
    assert np.abs(trained._pair_value_score(pairs)).max() < 1e-2


# ---------------------------------------------------------------------------------------------------- runs and saving


def test_checkpoint_with_buffers_resumes_where_it_stopped(trained_without_her, tmp_path):
    model = trained_without_her
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    with np.load(tmp_path / "buffer.high.npz", allow_pickle=False) as data:
        assert "preferences/labels" in data.files and "trajectories/lengths" in data.files

    resumed = PIPER.load(tmp_path / "model", env=short_maze(seed=1))
    resumed.load_replay_buffer(tmp_path / "buffer.pkl")
    assert resumed.high_replay_buffer_kwargs["n_sampled_goal"] == 0
    assert len(resumed.preferences) == len(model.preferences) > 0
    np.testing.assert_array_equal(resumed.preferences.all_pairs().labels, model.preferences.all_pairs().labels)
    assert len(resumed.trajectory_buffer) == len(model.trajectory_buffer) > 0
    assert resumed.higher.replay_buffer.pos == model.higher.replay_buffer.pos > 0
    assert resumed.higher.replay_buffer.reward_model is None  # saved with the model, given back at the next update
    resumed.learn(40, reset_num_timesteps=False)
    assert resumed.num_timesteps == 240
    assert resumed.higher.replay_buffer.reward_model is resumed.reward_model


def test_piper_no_v_with_two_envs_runs():
    env = short_maze(n_envs=2)
    model = tiny_piper(env, value_reg_coef=0.0)
    model.learn(160)
    assert model.num_timesteps == 160 and len(model.preferences) > 0
    action, _ = model.predict(env.reset(), deterministic=True)
    assert action.shape == (2, 2)


def test_her_off_conflicts_with_an_explicit_number_of_her_goals(maze_env):
    with pytest.raises(ValueError, match="high_her=False"):
        tiny_piper(maze_env, high_her=False, high_replay_buffer_kwargs=dict(n_sampled_goal=4))


# ---------------------------------------------------------------------------------------------------- learning


def held_out_accuracy(reward_model, data_model: PIPER) -> float:
    """Accuracy of ``reward_model`` on fresh PiL-labelled pairs of another run's trajectories."""
    rng = np.random.default_rng(3)
    pairs = sample_trajectory_pairs(data_model.trajectory_buffer, 1000, 0.8, data_model.subgoal_space, rng)
    labels = th.as_tensor(data_model.preference_pipeline.labeler.label(pairs))
    actions = th.as_tensor(pairs.actions.reshape(-1, pairs.actions.shape[-1]))
    with th.no_grad():
        step_rewards = reward_model(data_model._pair_observations(pairs), actions).reshape(pairs.mask.shape)
    _, logits = bradley_terry_loss(step_rewards, th.as_tensor(pairs.mask), labels)
    return preference_accuracy(logits, labels)


def test_the_reward_model_learns_to_rank_unseen_maze_trajectories():
    """After 1,500 steps r_phi ranks pairs from another run's episodes as the labels do (measured: 0.87-0.94; chance 0.5).

    PIPER-No-V labels (value_reg_coef=0) so that the check measures the goal-reaching signal, not the lower critic.
    """
    maze = dict(max_episode_steps=60)
    common = dict(option_steps=10, value_reg_coef=0.0, reward_model_kwargs=dict(net_arch=[64, 64]), trajectory_buffer_size=500)
    model = PIPER(
        "MultiInputPolicy",
        make_vec_env("sb3_dipper:PointMazeFourRooms-v0", n_envs=2, seed=1, env_kwargs=maze),
        learning_starts=600,
        buffer_size=20_000,
        batch_size=64,
        train_freq=4,
        low_policy_kwargs=dict(net_arch=[64, 64]),
        high_batch_size=64,
        policy_kwargs=dict(net_arch=[64, 64]),
        n_preference_pairs=1000,
        reward_batch_size=32,
        reward_gradient_steps=4,
        seed=1,
        **common,
    )
    model.learn(1500)
    # Another run's episodes (random behaviour, other start and goal cells), labelled by its own labeller.
    other = PIPER(
        "MultiInputPolicy",
        make_vec_env("sb3_dipper:PointMazeFourRooms-v0", n_envs=2, seed=51, env_kwargs=maze),
        learning_starts=10_000,
        seed=51,
        **common,
    )
    other.learn(1200)
    assert held_out_accuracy(model.reward_model, other) >= 0.75
