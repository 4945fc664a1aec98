"""Twin episodes: envs in pairs that replay the same episodes (EpisodeSeeds), one driven by DIPPER's policy and one by
the goal as every subgoal, and preference pairs that compare the two trajectories of one episode."""

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure

from sb3_dipper import DIPPER
from sb3_dipper.common.episode_seeds import EPISODE_SEED_KEY, EpisodeSeeds
from sb3_dipper.common.preferences import (
    PreferenceDataset,
    load_preference_data,
    policy_preferred_share,
    sample_trajectory_pairs,
    save_preference_data,
    twin_control_trajectories,
)
from sb3_dipper.common.trajectories import TrajectoryBuffer
from sb3_dipper.common.validation import InvalidSetting
from tests.conftest import SHORT_EPISODES, short_maze, tiny_model
from tests.test_preferences import OBS_SPACE, SPACE

TWINS = dict(twin_episodes=True, matched_control_prob=1.0)


def maze() -> gym.Env:
    return EpisodeSeeds(gym.make("sb3_dipper:PointMazeFourRooms-v0", **SHORT_EPISODES))


def starts(env: gym.Env, episodes: int, **reset_kwargs) -> list[np.ndarray]:
    """The start and goal of each of ``episodes`` resets."""
    return [
        np.concatenate([obs["achieved_goal"], obs["desired_goal"]])
        for obs, _ in (env.reset(**reset_kwargs) for _ in range(episodes))
    ]


def test_two_envs_seeded_alike_play_the_same_episodes_and_say_so():
    first, second = maze(), maze()
    first.seed_episodes(7)
    second.seed_episodes(7)
    # The second is stepped between its resets and handed another seed, the first not: the same episodes still.
    first_starts = starts(first, 3)
    second_starts = []
    for _ in range(3):
        obs, info = second.reset(seed=123)
        second_starts.append(np.concatenate([obs["achieved_goal"], obs["desired_goal"]]))
        *_, step_info = second.step(second.action_space.sample())
        assert step_info[EPISODE_SEED_KEY] == info[EPISODE_SEED_KEY]
    np.testing.assert_array_equal(first_starts, second_starts)
    assert len({tuple(start) for start in first_starts}) == 3, "each reset is a new episode"
    first.seed_episodes(8)
    assert not np.array_equal(starts(first, 3), first_starts), "another stream, other episodes"


def test_before_a_stream_is_set_the_wrapper_changes_nothing():
    wrapped, plain = maze(), gym.make("sb3_dipper:PointMazeFourRooms-v0", **SHORT_EPISODES)
    np.testing.assert_array_equal(starts(wrapped, 2, seed=3), starts(plain, 2, seed=3))
    _, info = wrapped.reset()
    *_, step_info = wrapped.step(wrapped.action_space.sample())
    assert EPISODE_SEED_KEY not in info and EPISODE_SEED_KEY not in step_info


def add_episode(buffer: TrajectoryBuffer, options: int, seed: int, goal_driven: bool, done_at_end: bool = True) -> None:
    """``options`` steps of one env whose points all sit at ``seed`` (so that a row tells its episode apart)."""
    for step in range(options):
        obs = {key: np.full((1, 2), float(seed), np.float32) for key in OBS_SPACE.spaces}
        done = np.array([done_at_end and step == options - 1])
        buffer.add(
            obs, np.zeros((1, 2), np.float32), np.full((1, 2), float(seed), np.float32), done,
            goal_driven=np.array([goal_driven]), episode_seeds=np.array([seed]),
        )  # fmt: skip


def twin_buffer() -> TrajectoryBuffer:
    """Rows: 0 the policy's episode 5, 1 the control's episode 5, 2 the policy's episode 6 (no twin stored), 3 the
    control's episode 9 (no policy twin), 4 a policy trajectory whose episode no stream seeded."""
    buffer = TrajectoryBuffer(capacity=8, max_length=3, observation_space=OBS_SPACE, action_dim=2)
    add_episode(buffer, 2, seed=5, goal_driven=False)
    add_episode(buffer, 2, seed=5, goal_driven=True)
    add_episode(buffer, 3, seed=6, goal_driven=False)
    add_episode(buffer, 1, seed=9, goal_driven=True)
    add_episode(buffer, 2, seed=-1, goal_driven=False)
    return buffer


def test_the_buffer_keeps_each_trajectorys_episode_seed_and_none_for_a_continuation():
    buffer = twin_buffer()
    np.testing.assert_array_equal(buffer.episode_seeds[:5], [5, 5, 6, 9, -1])
    # An episode longer than max_length=3 closes a trajectory at 3 options; the rest continues it: its twin's
    # continuation need not start where this one does, so it has no seed.
    add_episode(buffer, 4, seed=11, goal_driven=False)
    np.testing.assert_array_equal(buffer.episode_seeds[5:7], [11, -1])
    add_episode(buffer, 1, seed=12, goal_driven=False)
    assert buffer.episode_seeds[7] == 12, "the episode after a continuation starts one again"


def test_a_twin_pair_is_a_policy_trajectory_and_the_control_of_its_episode():
    buffer = twin_buffer()
    policy_rows, control_rows = twin_control_trajectories(buffer, 20, np.random.default_rng(0))
    np.testing.assert_array_equal(policy_rows, np.zeros(20))  # only row 0 has a twin stored
    np.testing.assert_array_equal(control_rows, np.ones(20))
    pairs = sample_trajectory_pairs(
        buffer, 20, 1.0, SPACE, np.random.default_rng(1), matched_control_prob=1.0, match_twins=True
    )
    np.testing.assert_array_equal(pairs.observations["observation"][:, :, 0], np.full((2, 20, 2), 5.0))
    np.testing.assert_array_equal(pairs.goal_driven, [[False] * 20, [True] * 20])
    no_twins = TrajectoryBuffer(capacity=4, max_length=3, observation_space=OBS_SPACE, action_dim=2)
    add_episode(no_twins, 2, seed=5, goal_driven=False)
    add_episode(no_twins, 2, seed=6, goal_driven=True)
    assert twin_control_trajectories(no_twins, 5, np.random.default_rng(0)) is None
    drawn = sample_trajectory_pairs(
        no_twins, 5, 0.0, SPACE, np.random.default_rng(0), matched_control_prob=1.0, match_twins=True
    )
    assert len(drawn) == 5, "without twins the pairs are drawn as without the switch"


def test_episode_seeds_round_trip_through_the_preference_file_and_an_older_file_knows_none(tmp_path):
    buffer = twin_buffer()
    save_preference_data(tmp_path / "prefs.npz", buffer, PreferenceDataset(10))
    restored = TrajectoryBuffer(capacity=8, max_length=3, observation_space=OBS_SPACE, action_dim=2)
    load_preference_data(tmp_path / "prefs.npz", restored, 10)
    np.testing.assert_array_equal(restored.episode_seeds, buffer.episode_seeds)
    with np.load(tmp_path / "prefs.npz") as stored:
        older = {key: value for key, value in stored.items() if key != "trajectories/episode_seeds"}
    np.savez(tmp_path / "older.npz", **older)
    load_preference_data(tmp_path / "older.npz", restored, 10)
    assert (restored.episode_seeds == -1).all() and (restored.lengths == buffer.lengths).all()
    np.savez(tmp_path / "bad.npz", **{**older, "trajectories/episode_seeds": np.full(8, -2)})
    with pytest.raises(ValueError, match="episode_seeds must hold integer seeds"):
        load_preference_data(tmp_path / "bad.npz", restored, 10)


def test_dipper_with_twin_episodes_compares_its_subgoals_with_the_goals_in_the_same_episodes(tmp_path):
    model = tiny_model(DIPPER, short_maze(n_envs=2, wrapper_class=EpisodeSeeds), switch_kwargs=TWINS)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(400, log_interval=1)
    logged = pd.read_csv(tmp_path / "progress.csv")
    gaps, preferred = (logged[f"train/high_new_{key}"].dropna() for key in ("start_gap", "policy_preferred"))
    assert len(gaps) > 0 and gaps.eq(0).all(), "twins start alike"
    assert len(preferred) > 0 and preferred.between(0, 1).all()
    buffer = model.trajectory_buffer
    stored = slice(0, len(buffer))
    driven, seeds = buffer.goal_driven[stored], buffer.episode_seeds[stored]
    assert driven.any() and not driven.all() and (seeds >= 0).all()
    # Every goal-driven episode has its policy twin, and the two started alike: same start, same goal.
    for control in np.flatnonzero(driven):
        twins = np.flatnonzero(~driven & (seeds == seeds[control]))
        assert len(twins) == 1
        for key in ("achieved_goal", "desired_goal"):
            np.testing.assert_array_equal(buffer.observations[key][twins[0], 0], buffer.observations[key][control, 0])
    pairs = model.preference_pipeline.sampler.sample(buffer, 30, np.random.default_rng(0))
    np.testing.assert_array_equal(pairs.goal_driven, [[False] * 30, [True] * 30])
    np.testing.assert_array_equal(pairs.observations["achieved_goal"][0, :, 0], pairs.observations["achieved_goal"][1, :, 0])
    goal_actions = model._subgoal_actions(pairs.observations["desired_goal"][1][pairs.mask[1]])
    np.testing.assert_allclose(pairs.actions[1][pairs.mask[1]], goal_actions, atol=1e-5)
    assert "goal_episode_success" in model._option_metric_keys()


@pytest.mark.parametrize(
    "env, switches, message",
    [
        (lambda: short_maze(n_envs=2), TWINS, r"needs every env wrapped in sb3_dipper.common.episode_seeds.EpisodeSeeds"),
        (lambda: short_maze(n_envs=3, wrapper_class=EpisodeSeeds), TWINS, "runs the envs in pairs, but the env has 3"),
        (lambda: short_maze(n_envs=2), dict(twin_episodes=True, goal_episode_prob=0.5), "chooses the goal-driven episodes"),
        (lambda: short_maze(n_envs=2), dict(twin_episodes="yes"), r"twin_episodes'\] must be True or False"),
    ],
)
def test_twin_episodes_refuse_what_they_cannot_pair(env, switches, message):
    with pytest.raises(InvalidSetting, match=message):
        tiny_model(DIPPER, env(), switch_kwargs=switches).learn(10)


def test_twin_episodes_resume_in_pairs_after_a_load(tmp_path):
    model = tiny_model(DIPPER, short_maze(n_envs=2, wrapper_class=EpisodeSeeds), switch_kwargs=TWINS)
    model.learn(200)
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    loaded = DIPPER.load(
        tmp_path / "model",
        env=make_vec_env(
            "sb3_dipper:PointMazeFourRooms-v0", n_envs=2, seed=5, env_kwargs=SHORT_EPISODES, wrapper_class=EpisodeSeeds
        ),
    )
    loaded.load_replay_buffer(tmp_path / "buffer.pkl")
    before = len(loaded.trajectory_buffer)
    loaded.learn(200, reset_num_timesteps=False)
    seeds = loaded.trajectory_buffer.episode_seeds[before : len(loaded.trajectory_buffer)]
    assert len(seeds) > 0 and (seeds >= 0).all()
    assert all((seeds == seed).sum() == 2 for seed in set(seeds[:-2].tolist())), "the new episodes are twins too"


def test_policy_preferred_share_reads_each_control_pairs_label_from_the_policys_side():
    pairs = sample_trajectory_pairs(twin_buffer(), 4, 0.0, SPACE, np.random.default_rng(0))
    pairs.goal_driven = np.array([[False, True, False, True], [True, False, False, True]])
    pairs.labels = np.array([1.0, 1.0, 0.0, 0.5], dtype=np.float32)
    # Pair 0: the policy's is tau^1 and preferred (1); pair 1: it is tau^2 and rejected (0); pairs 2, 3 are no contrast.
    assert policy_preferred_share(pairs) == 0.5
    pairs.labels = np.array([0.5, 0.0, 1.0, 1.0], dtype=np.float32)
    assert policy_preferred_share(pairs) == 0.75, "a tie counts half, tau^2 the policy's preferred counts whole"
    pairs.goal_driven = np.zeros((2, 4), dtype=bool)
    assert policy_preferred_share(pairs) is None


def test_twin_episodes_refuse_to_go_on_without_a_reset_on_an_env_not_seeded_in_pairs():
    model = tiny_model(DIPPER, short_maze(n_envs=2, wrapper_class=EpisodeSeeds), switch_kwargs=TWINS)
    model.learn(100)
    model.learn(100, reset_num_timesteps=False)  # the same env goes on: its streams are set
    model.set_env(short_maze(n_envs=2, seed=4, wrapper_class=EpisodeSeeds), force_reset=False)
    with pytest.raises(InvalidSetting, match=r"not \(set_env\(env, force_reset=False\)\?\): call set_env\(env\)"):
        model.learn(100, reset_num_timesteps=False)
    model.set_env(short_maze(n_envs=2, seed=4, wrapper_class=EpisodeSeeds))
    model.learn(100, reset_num_timesteps=False)
    assert all(model.env.get_attr("episodes_seeded"))
