"""DPO-FLAT: segment pairs and their labels by hand, the DPO step, its episode store, the NLL term, errors and a learning
check (its runs, saving and seeding: tests/test_run.py, tests/test_save_load.py)."""

import copy
import math

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.distributions import SquashedDiagGaussianDistribution
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure
from stable_baselines3.common.vec_env import VecNormalize

from sb3_dipper.common.losses import dipper_logits
from sb3_dipper.common.preferences import PreferenceDataset, PrimitiveInTheLoopLabeler, TrajectoryPairs
from sb3_dipper.common.trajectories import TrajectoryBuffer
from sb3_dipper.dpo_flat import DPOFlat, sample_segment_pairs
from tests.conftest import short_maze

TINY = dict(
    segment_length=5,
    learning_starts=40,
    n_preference_pairs=200,
    pairs_per_batch=8,
    trajectory_buffer_size=50,
    policy_kwargs=dict(net_arch=[16]),
    seed=0,
)

# ---------------------------------------------------------------------------------------------------- segment pairs

GOAL_KEYS = ("observation", "achieved_goal", "desired_goal")
OBS_SPACE = spaces.Dict({key: spaces.Box(-np.inf, np.inf, (2,), np.float32) for key in GOAL_KEYS})
LENGTHS = [8, 8, 3]


def goal_reached(achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
    return np.linalg.norm(achieved - desired, axis=-1) <= 0.5


@pytest.fixture
def buffer() -> TrajectoryBuffer:
    """Episode e walks along x from 10 e, one unit a step: step t is at (10 e + t, 0), then at (10 e + t + 1, 0).

    ``observation`` is (e, t) and the action is (e, t) / 100, so every stored value says where it came from.
    """
    buffer = TrajectoryBuffer(capacity=5, max_length=8, observation_space=OBS_SPACE, action_dim=2)
    for episode, length in enumerate(LENGTHS):
        for step in range(length):
            obs = {
                "observation": np.array([[episode, step]], dtype=np.float32),
                "achieved_goal": np.array([[10 * episode + step, 0]], dtype=np.float32),
                "desired_goal": np.array([[100 + episode, 0]], dtype=np.float32),
            }
            action = np.array([[episode, step]], dtype=np.float32) / 100
            next_achieved = np.array([[10 * episode + step + 1, 0]], dtype=np.float32)
            buffer.add(obs, action, next_achieved, np.array([step == length - 1]))
    return buffer


def test_segments_are_consecutive_steps_of_one_episode(buffer):
    pairs = sample_segment_pairs(buffer, 200, segment_length=5, hindsight_goal_prob=0.0, rng=np.random.default_rng(0))
    episode, step = pairs.observations["observation"][..., 0], pairs.observations["observation"][..., 1]
    mask = pairs.mask
    assert pairs.actions.shape == (2, 200, 5, 2) and mask.shape == (2, 200, 5)
    # Real steps: one episode, consecutive steps; the "actions" are the stored primitive actions.
    assert np.all(episode[mask] == np.broadcast_to(episode[..., :1], episode.shape)[mask])
    assert np.all(np.diff(step, axis=-1)[mask[..., 1:]] == 1)
    np.testing.assert_allclose(pairs.actions[mask] * 100, pairs.observations["observation"][mask], atol=1e-4)
    np.testing.assert_array_equal(pairs.reached_actions, pairs.actions)
    # A segment of an 8-step episode fits whole (start 0 to 3); the 3-step episode gives a masked 3-step segment.
    long_episode = episode[..., 0] < 2
    assert mask[long_episode].all() and set(step[..., 0][long_episode]) == {0, 1, 2, 3}
    np.testing.assert_array_equal(mask[~long_episode], [[True, True, True, False, False]] * int((~long_episode).sum()))
    # Without hindsight goals each segment keeps its episode's goal.
    np.testing.assert_array_equal(pairs.observations["desired_goal"][..., 0][mask], 100 + episode[mask])


def test_shared_hindsight_goals_and_primitive_in_the_loop_labels(buffer):
    pairs = sample_segment_pairs(buffer, 300, segment_length=5, hindsight_goal_prob=1.0, rng=np.random.default_rng(1))
    goals = pairs.observations["desired_goal"]
    # Both segments, at every step, share one goal: a position one of them reached.
    assert np.all(goals == goals[:1, :, :1])
    reached = goal_reached(pairs.next_achieved_goals, goals) & pairs.mask
    assert np.all(reached.any(axis=0).any(axis=-1))
    # Positions are one unit apart, so a segment reaches the goal at most once: the one that reaches it is preferred,
    # and when both do (they overlap in one episode) or neither does, the pair is a tie.
    labels = PrimitiveInTheLoopLabeler(goal_reached).label(pairs)
    counts = reached.sum(axis=-1)
    assert counts.max() == 1
    np.testing.assert_array_equal(labels, np.where(counts[0] > counts[1], 1.0, np.where(counts[0] < counts[1], 0.0, 0.5)))
    assert {0.0, 0.5, 1.0} == set(labels)


def test_sampling_needs_a_finished_episode():
    empty = TrajectoryBuffer(capacity=2, max_length=4, observation_space=OBS_SPACE, action_dim=2)
    with pytest.raises(ValueError, match="at least one finished episode"):
        sample_segment_pairs(empty, 1, 2, 0.8, np.random.default_rng(0))


def test_one_dpo_step_by_hand():
    """A pair's logit is z = beta * sum_t (log pi(a^1_t) - log u) - beta * sum_t (log pi(a^2_t) - log u), with u = 1/4 the
    uniform density on [-1, 1]^2; the loss is the mean of -[y log sigmoid(z) + (1 - y) log sigmoid(-z)]; a step lowers it.

    Pair 0: two full 2-step segments, the first preferred. Pair 1: a tie between a 2-step segment and a 1-step one (its
    second step masked), where the reference terms do not cancel.
    """
    model = DPOFlat("MultiInputPolicy", short_maze(), beta=0.5, learning_rate=1e-2, **{**TINY, "segment_length": 2})
    model.set_logger(configure(None, []))
    rng = np.random.default_rng(0)
    shapes = {"observation": 4, "achieved_goal": 2, "desired_goal": 2}
    mask = np.ones((2, 2, 2), dtype=bool)
    mask[1, 1, 1] = False
    pairs = TrajectoryPairs(
        observations={key: rng.normal(size=(2, 2, 2, size)).astype(np.float32) for key, size in shapes.items()},
        actions=rng.uniform(-0.9, 0.9, size=(2, 2, 2, 2)).astype(np.float32),
        reached_actions=np.zeros((2, 2, 2, 2), np.float32),
        next_achieved_goals=np.zeros((2, 2, 2, 2), np.float32),
        mask=mask,
        labels=np.array([1.0, 0.5], dtype=np.float32),
    )
    # A full dataset: the training round has nothing new to label and trains on these pairs.
    model.preferences = PreferenceDataset(2)
    model.preferences.add(pairs)
    model.preference_pipeline.labeler = PrimitiveInTheLoopLabeler(goal_reached)
    reference = math.log(1 / 4)

    def loss_by_hand() -> float:
        observations, actions, _, _ = model._pair_tensors(pairs)
        with th.no_grad():
            mean, log_std, _ = model.policy.actor.get_action_dist_params(observations)
            distribution = SquashedDiagGaussianDistribution(2).proba_distribution(mean, log_std)
            log_probs = distribution.log_prob(actions).reshape(2, 2, 2).numpy()
        implicit_rewards = 0.5 * ((log_probs - reference) * mask).sum(axis=-1)
        logits = implicit_rewards[0] - implicit_rewards[1]
        # -log sigmoid(z) = log(1 + e^-z); a tie: (log(1 + e^-z) + log(1 + e^z)) / 2.
        preferred = math.log1p(math.exp(-logits[0]))
        tie = 0.5 * (math.log1p(math.exp(-logits[1])) + math.log1p(math.exp(logits[1])))
        return (preferred + tie) / 2

    before = loss_by_hand()
    # Pairs are drawn with replacement: seed the draw so that the batch of two holds each pair once.
    model._rng = np.random.default_rng(1)
    assert sorted(np.random.default_rng(1).integers(2, size=2).tolist()) == [0, 1]
    model.train(gradient_steps=1, batch_size=2)
    assert model.logger.name_to_value["train/dpo_loss"] == pytest.approx(before, rel=1e-3)
    assert model.logger.name_to_value["train/pref_accuracy"] in (0.0, 1.0)  # only pair 0 is strict
    assert loss_by_hand() < before


# ----------------------------------------------------------------------------------------------- episodes, NLL term, errors


def test_every_primitive_step_is_stored_in_its_episode():
    model = DPOFlat("MultiInputPolicy", short_maze(), random_action_prob=1.0, **TINY)
    model.learn(40)  # two 20-step episodes of uniform random actions
    assert len(model.trajectory_buffer) == 2 and model.trajectory_buffer.lengths[:2].tolist() == [20, 20]
    actions = model.trajectory_buffer.actions[:2]
    assert np.all(np.abs(actions) <= 1.0) and actions.std() > 0.3
    # next achieved goals chain with the next step's achieved goal inside an episode
    np.testing.assert_allclose(
        model.trajectory_buffer.next_achieved_goals[:2, :-1], model.trajectory_buffer.observations["achieved_goal"][:2, 1:]
    )


def test_nll_term_vec_normalize_and_checkpoints(tmp_path):
    env = VecNormalize(short_maze(), norm_obs=True, norm_reward=False)
    model = DPOFlat(
        "MultiInputPolicy",
        env,
        nll_coef=1.0,
        policy_kwargs=dict(net_arch=[16], acting_tau=0.05),
        **{key: value for key, value in TINY.items() if key != "policy_kwargs"},
    )
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(200, log_interval=1)
    assert "train/nll" in open(tmp_path / "progress.csv").readline()
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    resumed = DPOFlat.load(tmp_path / "model")
    resumed.load_replay_buffer(tmp_path / "buffer.pkl")
    resumed.set_env(env)
    assert len(resumed.preferences) == len(model.preferences) > 0
    np.testing.assert_array_equal(resumed.preferences.all_pairs().labels, model.preferences.all_pairs().labels)
    assert len(resumed.trajectory_buffer) == len(model.trajectory_buffer)
    resumed.learn(100, reset_num_timesteps=False)
    assert resumed.num_timesteps == 300


def test_bad_input_gives_clear_errors():
    with pytest.raises(ValueError, match=r"segment_length \(25\) is longer than an episode"):
        DPOFlat("MultiInputPolicy", short_maze(), segment_length=25)
    with pytest.raises(ValueError, match="random_action_prob"):
        DPOFlat("MultiInputPolicy", short_maze(), random_action_prob=1.5)


# ---------------------------------------------------------------------------------------------------- learning


def test_the_policy_learns_preferences_it_was_not_shown():
    """After 2000 steps the policy's implicit reward ranks labelled pairs from unseen episodes.

    Accuracy on the strict pairs, untrained -> trained, measured for seeds 0, 1, 2: 0.44 -> 0.95, 0.50 -> 0.97, 0.56 -> 0.99.
    """
    kwargs = {**TINY, "segment_length": 10, "learning_starts": 300, "n_preference_pairs": 2000, "pairs_per_batch": 32}
    kwargs.update(train_freq=2, learning_rate=1e-3, policy_kwargs=dict(net_arch=[64, 64]))
    model = DPOFlat("MultiInputPolicy", maze_of_50_steps(seed=0), **kwargs)
    untrained = copy.deepcopy(model.policy)
    model.learn(2000)

    # Unseen episodes: the trained policy, exploring, from other starts toward other goals (no training there).
    held_out = DPOFlat("MultiInputPolicy", maze_of_50_steps(seed=7), **{**kwargs, "learning_starts": 0, "gradient_steps": 0})
    held_out.policy.load_state_dict(model.policy.state_dict())
    held_out.learn(500)
    pairs = sample_segment_pairs(held_out.trajectory_buffer, 1000, 10, 0.8, np.random.default_rng(123))
    pairs.labels = model.preference_pipeline.labeler.label(pairs)
    strict = pairs.labels != 0.5

    def accuracy(policy) -> float:
        observations, actions, mask, _ = model._pair_tensors(pairs)
        with th.no_grad():
            logits = dipper_logits(policy.log_prob(observations, actions).reshape(mask.shape), mask, beta=1.0).numpy()
        return float(np.mean((logits[strict] > 0) == (pairs.labels[strict] > 0.5)))

    assert strict.sum() > 300
    assert accuracy(untrained) < 0.65 and accuracy(model.policy) > 0.85


def maze_of_50_steps(seed: int):
    return make_vec_env("sb3_dipper:PointMazeFourRooms-v0", seed=seed, env_kwargs={"max_episode_steps": 50})
