"""Preference pairs: primitive-in-the-loop scores and labels, ties, hindsight goal sharing, the stored dataset, and the
pipeline that labels pairs on schedule and saves itself."""

import numpy as np
import pytest
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env

from sb3_dipper import DIPPER
from sb3_dipper.common.preference_pipeline import PreferencePipeline
from sb3_dipper.common.preferences import (
    MAX_NEW_PAIRS_PER_ROUND,
    PreferenceDataset,
    PreferenceSource,
    PrimitiveInTheLoopLabeler,
    SegmentPairSampler,
    TrajectoryPairs,
    TrajectoryPairSampler,
    cut_option_segments,
    final_goal_distances,
    final_path_distances,
    goal_distance_gains,
    labels_from_scores,
    load_preference_data,
    pairs_due,
    path_distance_gains,
    progress_gain_labels,
    progress_labels,
    relabel_hindsight_actions,
    sample_trajectory_pairs,
    save_preference_data,
    start_gaps,
    truncate_at_first_arrival,
)
from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.common.trajectories import TrajectoryBuffer
from sb3_dipper.envs.fetch import MazeGeometry
from sb3_dipper.labelling.sources import ProgressTieBreaker, preference_source_from
from tests.conftest import tiny_model

SPACE = SubgoalSpace(low=np.full(2, -5.0), high=np.full(2, 5.0), threshold=0.5)
OBS_SPACE = spaces.Dict(
    {key: spaces.Box(-10, 10, (2,), np.float32) for key in ("observation", "achieved_goal", "desired_goal")}
)
GOAL = np.array([3.0, 0.0], dtype=np.float32)


def goal_reached(achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
    return np.linalg.norm(achieved - desired, axis=-1) <= 0.5


def add_trajectory(
    buffer: TrajectoryBuffer,
    path: list[tuple[float, float]],
    goal: np.ndarray = GOAL,
    goal_driven: list[bool] | None = None,
    start: tuple[float, float] = (0.0, 0.0),
) -> None:
    position = np.array(start, dtype=np.float32)
    for step, point in enumerate(path):
        obs = {"observation": position[None], "achieved_goal": position[None], "desired_goal": goal[None]}
        done = np.array([step == len(path) - 1])
        driven = None if goal_driven is None else np.array([goal_driven[step]])
        buffer.add(obs, np.zeros((1, 2), np.float32), np.array([point], dtype=np.float32), done, goal_driven=driven)
        position = np.array(point, dtype=np.float32)


@pytest.fixture
def buffer() -> TrajectoryBuffer:
    buffer = TrajectoryBuffer(capacity=10, max_length=3, observation_space=OBS_SPACE, action_dim=2)
    add_trajectory(buffer, [(1, 0), (2, 0), (3, 0)])  # 0: reaches GOAL at its last option
    add_trajectory(buffer, [(0, 1), (0, 2), (0, 3)])  # 1: never reaches GOAL
    add_trajectory(buffer, [(3, 0.2), (2, 2), (0, 0)])  # 2: reaches GOAL first, then leaves
    add_trajectory(buffer, [(1, 1), (3, 0.1)])  # 3: two options only, reaches GOAL at the second
    return buffer


def pairs_of(buffer: TrajectoryBuffer, first: list[int], second: list[int]) -> TrajectoryPairs:
    indices = np.array([first, second])
    next_achieved = buffer.next_achieved_goals[indices]
    return TrajectoryPairs(
        observations={key: value[indices].copy() for key, value in buffer.observations.items()},
        actions=buffer.actions[indices],
        reached_actions=relabel_hindsight_actions(next_achieved, SPACE),
        next_achieved_goals=next_achieved,
        mask=np.stack([buffer.mask(indices[0]), buffer.mask(indices[1])]),
        labels=np.full(len(first), np.nan, dtype=np.float32),
    )


def test_trajectory_buffer_stores_whole_episodes_with_a_mask(buffer):
    assert len(buffer) == 4
    assert buffer.lengths[:4].tolist() == [3, 3, 3, 2]
    assert buffer.mask(np.array([3])).tolist() == [[True, True, False]]
    np.testing.assert_allclose(buffer.observations["achieved_goal"][0, 1], [1, 0])


def test_primitive_in_the_loop_scores_count_options_that_end_at_the_goal(buffer):
    labeler = PrimitiveInTheLoopLabeler(goal_reached)
    pairs = pairs_of(buffer, [0, 0, 1, 2], [1, 2, 1, 3])
    np.testing.assert_array_equal(labeler.scores(pairs), [[1, 1, 0, 1], [0, 1, 0, 1]])
    np.testing.assert_array_equal(labeler.label(pairs), [1.0, 0.5, 0.5, 0.5])


def test_labels_from_scores_prefer_higher_and_tie_at_equal():
    np.testing.assert_array_equal(labels_from_scores(np.array([[2, 0, 1], [1, 3, 1]])), [1.0, 0.0, 0.5])


def test_value_score_breaks_ties(buffer):
    labeler = PrimitiveInTheLoopLabeler(goal_reached, value_score=lambda pairs: np.array([[0.0], [1e-3]]))
    assert labeler.label(pairs_of(buffer, [0], [2])).tolist() == [0.0]


def test_truncation_prefers_the_earliest_arrival(buffer):
    labeler = PrimitiveInTheLoopLabeler(goal_reached)
    pairs = truncate_at_first_arrival(pairs_of(buffer, [0, 3, 1], [2, 0, 1]), goal_reached)
    # Trajectory 2 arrives after one option, 0 after three; 3 arrives after two (before 0); 1 and 1 never arrive.
    np.testing.assert_array_equal(pairs.mask[:, 0], [[True, False, False], [True, False, False]])
    np.testing.assert_array_equal(labeler.label(pairs), [0.0, 1.0, 0.5])
    np.testing.assert_array_equal(pairs.mask[:, 2], [[True, True, True], [True, True, True]])


def test_hindsight_goal_sharing_gives_both_trajectories_a_goal_one_of_them_achieved(buffer):
    rng = np.random.default_rng(0)
    pairs = sample_trajectory_pairs(buffer, 50, hindsight_goal_prob=1.0, subgoal_space=SPACE, rng=rng)
    goals = pairs.observations["desired_goal"]
    np.testing.assert_array_equal(goals[0], goals[1])
    for pair in range(50):
        achieved = np.concatenate([pairs.next_achieved_goals[side, pair][pairs.mask[side, pair]] for side in (0, 1)])
        assert np.any(np.all(np.isclose(achieved, goals[0, pair, 0]), axis=1))
        assert np.all(goals[:, pair] == goals[0, pair, 0])


def test_without_hindsight_each_trajectory_keeps_its_own_goal():
    buffer = TrajectoryBuffer(capacity=4, max_length=2, observation_space=OBS_SPACE, action_dim=2)
    add_trajectory(buffer, [(1, 0), (2, 0)], goal=np.array([1.0, 1.0], np.float32))
    add_trajectory(buffer, [(0, 1), (0, 2)], goal=np.array([-1.0, -1.0], np.float32))
    pairs = sample_trajectory_pairs(buffer, 20, hindsight_goal_prob=0.0, subgoal_space=SPACE, rng=np.random.default_rng(1))
    stored_goals = buffer.observations["desired_goal"][:2, 0]
    for side in (0, 1):
        for pair in range(20):
            assert any(np.allclose(pairs.observations["desired_goal"][side, pair, 0], goal) for goal in stored_goals)


def test_a_trajectory_is_goal_driven_only_if_every_step_was():
    buffer = TrajectoryBuffer(capacity=4, max_length=2, observation_space=OBS_SPACE, action_dim=2)
    add_trajectory(buffer, [(1, 0), (2, 0)], goal_driven=[True, True])
    add_trajectory(buffer, [(1, 0), (2, 0)], goal_driven=[False, True])  # the goal took over mid-episode
    add_trajectory(buffer, [(1, 0), (2, 0)])  # no step's driver given
    buffer.add(*_one_step(), np.array([False]), goal_driven=np.array([True]))
    buffer.discard_open()  # an interrupted goal-driven episode does not mark the next
    add_trajectory(buffer, [(1, 0), (2, 0)], goal_driven=[False, False])
    assert buffer.goal_driven.tolist() == [True, False, False, False]


def _one_step() -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    zero = np.zeros((1, 2), np.float32)
    return {"observation": zero, "achieved_goal": zero, "desired_goal": GOAL[None]}, zero, zero


def test_a_pair_of_the_goal_driven_control_and_another_keeps_the_envs_goals():
    buffer = TrajectoryBuffer(capacity=4, max_length=2, observation_space=OBS_SPACE, action_dim=2)
    add_trajectory(buffer, [(1, 0), (2, 0)], goal=np.array([1.0, 1.0], np.float32), goal_driven=[True, True])
    add_trajectory(buffer, [(0, 1), (0, 2)], goal=np.array([-1.0, -1.0], np.float32))
    add_trajectory(buffer, [(0, -1), (0, -2)], goal=np.array([-1.0, 1.0], np.float32))
    pairs = sample_trajectory_pairs(buffer, 200, hindsight_goal_prob=1.0, subgoal_space=SPACE, rng=np.random.default_rng(2))
    goals = pairs.observations["desired_goal"][:, :, 0]
    stored = buffer.observations["desired_goal"][:3, 0]
    contrast = 0
    for pair in range(200):
        own = [np.any(np.all(goals[side, pair] == stored, axis=1)) for side in (0, 1)]
        shared = np.array_equal(goals[0, pair], goals[1, pair])
        # Which trajectories the pair holds, told by their stored goals (each trajectory here has its own).
        drivers = {int(np.flatnonzero(np.all(goals[side, pair] == stored, axis=1))[0]) == 0 for side in (0, 1) if own[side]}
        if len(drivers) == 2:  # the goal-driven trajectory and a policy's: both keep the env's goals
            contrast += 1
            assert all(own) and not shared
        else:
            assert shared  # every other pair shares a hindsight goal (hindsight_goal_prob=1)
        # The sampler says so itself, and which side the goal drove.
        assert pairs.shared_goal[pair] == (len(drivers) != 2)
        assert [bool(pairs.goal_driven[side, pair]) for side in (0, 1) if own[side]] == [
            bool(np.all(goals[side, pair] == stored[0])) for side in (0, 1) if own[side]
        ]
    assert contrast > 20
    kept = truncate_at_first_arrival(pairs, lambda achieved, goal: np.zeros(achieved.shape[:-1], bool)).select(np.arange(5))
    np.testing.assert_array_equal(kept.shared_goal, pairs.shared_goal[:5])
    np.testing.assert_array_equal(kept.goal_driven, pairs.goal_driven[:, :5])


def test_without_contrast_env_goals_a_contrast_pair_takes_a_hindsight_goal_from_the_same_draws():
    buffer = TrajectoryBuffer(capacity=4, max_length=2, observation_space=OBS_SPACE, action_dim=2)
    add_trajectory(buffer, [(1, 0), (2, 0)], goal=np.array([1.0, 1.0], np.float32), goal_driven=[True, True])
    add_trajectory(buffer, [(0, 1), (0, 2)], goal=np.array([-1.0, -1.0], np.float32))
    kept, hindsight = (
        sample_trajectory_pairs(buffer, 100, 1.0, SPACE, np.random.default_rng(3), contrast_env_goals=contrast)
        for contrast in (True, False)
    )
    goals = hindsight.observations["desired_goal"][:, :, 0]
    assert np.array_equal(goals[0], goals[1]), "every pair shares a hindsight goal (hindsight_goal_prob=1)"
    np.testing.assert_array_equal(kept.observations["observation"], hindsight.observations["observation"])
    differs = np.any(kept.observations["desired_goal"] != hindsight.observations["desired_goal"], axis=(0, 2, 3))
    contrast = np.any(kept.observations["desired_goal"][0, :, 0] != kept.observations["desired_goal"][1, :, 0], axis=-1)
    assert contrast.any() and np.array_equal(differs, contrast), "only the contrast pairs' goals differ"


def matched_buffer() -> TrajectoryBuffer:
    """Two goal-driven trajectories (rows 0, 1) and two of the policy's (rows 2, 3), each policy trajectory starting
    near one control: row 2 near row 1, row 3 near row 0."""
    buffer = TrajectoryBuffer(capacity=6, max_length=2, observation_space=OBS_SPACE, action_dim=2)
    west, east = np.array([-3.0, 0.0], np.float32), np.array([3.0, 0.0], np.float32)
    add_trajectory(buffer, [(1, 0), (2, 0)], goal=east, goal_driven=[True, True], start=(0.0, 0.0))
    add_trajectory(buffer, [(-3, 1), (-3, 0)], goal=west, goal_driven=[True, True], start=(-4.0, 1.0))
    add_trajectory(buffer, [(0, 1), (0, 2)], goal=np.array([-3.0, 0.4], np.float32), start=(-4.0, 1.3))
    add_trajectory(buffer, [(0, -1), (0, -2)], goal=east, start=(0.0, 0.4))
    return buffer


def test_a_matched_pair_is_a_policy_trajectory_and_the_control_that_started_nearest_it():
    pairs = sample_trajectory_pairs(matched_buffer(), 40, 1.0, SPACE, np.random.default_rng(4), matched_control_prob=1.0)
    starts = pairs.observations["achieved_goal"][:, :, 0]
    from_west = starts[0, :, 0] < -2
    assert from_west.any() and not from_west.all()
    # tau^1 is the policy's (rows 2, 3), tau^2 the control nearest it (rows 1, 0), both with the env's goals.
    np.testing.assert_array_equal(starts[1, from_west], [[-4.0, 1.0]] * from_west.sum())
    np.testing.assert_array_equal(starts[1, ~from_west], [[0.0, 0.0]] * (~from_west).sum())
    # Start gaps by hand: (0.3 in the achieved goal, 0.4 in the goal) from the west, (0.4, 0) from the east.
    np.testing.assert_allclose(start_gaps(pairs), np.where(from_west, 0.5, 0.4), rtol=1e-6)


def test_without_matched_pairs_the_draws_are_unchanged_and_a_buffer_without_controls_draws_at_random():
    buffer = matched_buffer()
    default, off = (
        sample_trajectory_pairs(buffer, 30, 0.5, SPACE, np.random.default_rng(5), **extra)
        for extra in ({}, {"matched_control_prob": 0.0})
    )
    np.testing.assert_array_equal(default.observations["achieved_goal"], off.observations["achieved_goal"])
    np.testing.assert_array_equal(default.observations["desired_goal"], off.observations["desired_goal"])
    no_controls = TrajectoryBuffer(capacity=4, max_length=2, observation_space=OBS_SPACE, action_dim=2)
    add_trajectory(no_controls, [(1, 0), (2, 0)])
    add_trajectory(no_controls, [(0, 1), (0, 2)], start=(1.0, 1.0))
    pairs = sample_trajectory_pairs(no_controls, 30, 0.0, SPACE, np.random.default_rng(6), matched_control_prob=1.0)
    assert len(pairs) == 30 and (start_gaps(pairs) > 0).any()


def test_hindsight_actions_are_the_reached_subgoals_in_unit_coordinates(buffer):
    pairs = pairs_of(buffer, [0], [1])
    np.testing.assert_allclose(pairs.reached_actions[0, 0], [[0.2, 0.0], [0.4, 0.0], [0.6, 0.0]])


def test_dataset_respects_the_label_budget_and_round_trips_through_npz(buffer, tmp_path):
    labeler = PrimitiveInTheLoopLabeler(goal_reached)
    dataset = PreferenceDataset(capacity=5)
    for _ in range(3):
        pairs = pairs_of(buffer, [0, 1], [1, 2])
        pairs.labels = labeler.label(pairs)
        dataset.add(pairs)
    assert len(dataset) == 5 and dataset.remaining == 0
    dataset.save(tmp_path / "prefs.npz")
    loaded = PreferenceDataset.load(tmp_path / "prefs.npz")
    assert loaded.capacity == 5 and len(loaded) == 5
    original, restored = dataset.all_pairs(), loaded.all_pairs()
    np.testing.assert_array_equal(original.labels, restored.labels)
    np.testing.assert_array_equal(original.mask, restored.mask)
    np.testing.assert_allclose(original.observations["desired_goal"], restored.observations["desired_goal"])


def test_labels_are_due_in_step_with_training_and_capped_per_round(buffer):
    dataset = PreferenceDataset(capacity=1000)
    assert pairs_due(dataset, 1000, num_timesteps=0, total_timesteps=100) == 1
    assert pairs_due(dataset, 1000, num_timesteps=10, total_timesteps=100) == 100
    assert pairs_due(dataset, 1000, num_timesteps=100, total_timesteps=100) == MAX_NEW_PAIRS_PER_ROUND
    pairs = pairs_of(buffer, [0, 1], [1, 2])
    pairs.labels = PrimitiveInTheLoopLabeler(goal_reached).label(pairs)
    dataset.add(pairs)
    assert pairs_due(dataset, 1000, num_timesteps=10, total_timesteps=100) == 98
    full = PreferenceDataset(capacity=2)
    full.add(pairs)
    assert pairs_due(full, 2, num_timesteps=100, total_timesteps=100) == 0


def test_checkpointed_trajectories_and_pairs_are_restored(buffer, tmp_path):
    dataset = PreferenceDataset(capacity=10)
    pairs = pairs_of(buffer, [0, 1], [1, 2])
    pairs.labels = PrimitiveInTheLoopLabeler(goal_reached).label(pairs)
    dataset.add(pairs)
    save_preference_data(tmp_path / "high.npz", buffer, dataset)
    restored_buffer = TrajectoryBuffer(capacity=10, max_length=3, observation_space=OBS_SPACE, action_dim=2)
    restored = load_preference_data(tmp_path / "high.npz", restored_buffer, label_budget=10)
    assert len(restored) == 2 and restored.capacity == 10 and len(restored_buffer) == len(buffer)
    np.testing.assert_array_equal(restored.all_pairs().labels, dataset.all_pairs().labels)


def test_trajectories_saved_before_they_recorded_their_driver_load_as_nobodys_control(buffer, tmp_path):
    save_preference_data(tmp_path / "high.npz", buffer, PreferenceDataset(capacity=10))
    with np.load(tmp_path / "high.npz") as saved:
        arrays = {key: saved[key] for key in saved.files if key != "trajectories/goal_driven"}
    np.savez(tmp_path / "old.npz", **arrays)
    restored = TrajectoryBuffer(capacity=10, max_length=3, observation_space=OBS_SPACE, action_dim=2)
    restored.goal_driven[:] = True
    load_preference_data(tmp_path / "old.npz", restored, label_budget=10)
    assert not restored.goal_driven.any() and len(restored) == len(buffer)
    arrays["trajectories/goal_driven"] = np.full(10, 2)
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match="trajectories/goal_driven must hold booleans"):
        load_preference_data(tmp_path / "bad.npz", restored, label_budget=10)


def test_unlabelled_pairs_are_refused(buffer):
    with pytest.raises(ValueError, match="labelled"):
        PreferenceDataset(capacity=2).add(pairs_of(buffer, [0], [1]))


def _valid_arrays(buffer: TrajectoryBuffer) -> dict[str, np.ndarray]:
    pairs = pairs_of(buffer, [0], [1])
    pairs.labels = np.array([1.0], np.float32)
    dataset = PreferenceDataset(capacity=1)
    dataset.add(pairs)
    return dataset.to_arrays()


@pytest.mark.parametrize(
    "corrupt, message",
    [
        (lambda arrays: arrays.pop("labels"), "missing"),
        (lambda arrays: arrays.update(labels=np.array([0.7], np.float32)), "labels must be"),
        (lambda arrays: arrays.update(mask=np.ones((2, 3), bool)), "mask must have shape"),
        (lambda arrays: arrays.update(actions=np.zeros((2, 1, 5, 2), np.float32)), "actions must start with shape"),
    ],
)
def test_malformed_preference_files_give_a_clear_error(buffer, tmp_path, corrupt, message):
    arrays = _valid_arrays(buffer)
    corrupt(arrays)
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match=f"Malformed preference file.*{message}"):
        PreferenceDataset.load(tmp_path / "bad.npz")


def test_pickled_preference_files_are_refused(tmp_path):
    np.savez(tmp_path / "pickled.npz", labels=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match="Malformed preference file"):
        PreferenceDataset.load(tmp_path / "pickled.npz")


def test_progress_labels_prefer_the_trajectory_that_ends_nearer_the_goal(buffer):
    pairs = pairs_of(buffer, [0, 1, 2, 3], [1, 2, 3, 0])
    # Final options end at (3, 0), (0, 3), (0, 0) and (3, 0.1) (trajectory 3 has two options); GOAL is (3, 0).
    np.testing.assert_allclose(
        final_goal_distances(pairs), [[0.0, np.sqrt(18.0), 3.0, 0.1], [np.sqrt(18.0), 3.0, 0.1, 0.0]], atol=1e-6
    )
    np.testing.assert_array_equal(progress_labels(pairs), [1.0, 0.0, 0.0, 0.0])


@pytest.mark.parametrize("spec", ["progress", {"kind": "progress"}])
def test_progress_tie_breaker_answers_only_the_scripts_ties(buffer, spec):
    pairs = pairs_of(buffer, [0, 1, 2, 3], [1, 2, 3, 0])
    script = PrimitiveInTheLoopLabeler(goal_reached)
    # Trajectories 0, 2 and 3 each end one option at GOAL, 1 none: pairs (2, 3) and (3, 0) are ties.
    np.testing.assert_array_equal(script.label(pairs), [1.0, 0.0, 0.5, 0.5])
    source = preference_source_from(spec, script)
    assert isinstance(source, ProgressTieBreaker) and source.script is script
    np.testing.assert_array_equal(source.label(pairs), [1.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="ProgressTieBreaker needs a script"):
        ProgressTieBreaker().label(pairs)
    with pytest.raises(ValueError, match="preference_source"):
        preference_source_from("progress:3", script)


@pytest.mark.parametrize("spec", ["progress:gain", {"kind": "progress", "measure": "gain"}])
def test_the_gain_answers_ties_by_the_progress_each_trajectory_made_not_where_it_began(spec):
    buffer = TrajectoryBuffer(capacity=4, max_length=2, observation_space=OBS_SPACE, action_dim=2)
    # Neither reaches GOAL (3, 0): trajectory 0 starts 1 away and ends 1.5 away (gain -0.5); trajectory 1 starts 6 away
    # and ends 2 away (gain 4).
    add_trajectory(buffer, [(2.0, 1.0), (1.5, 0.0)], start=(2.0, 0.0))
    add_trajectory(buffer, [(-1.0, 0.0), (1.0, 0.0)], start=(-3.0, 0.0))
    pairs = pairs_of(buffer, [0, 1], [1, 0])
    np.testing.assert_allclose(goal_distance_gains(pairs), [[-0.5, 4.0], [4.0, -0.5]], atol=1e-6)
    np.testing.assert_array_equal(progress_gain_labels(pairs), [0.0, 1.0])
    script = PrimitiveInTheLoopLabeler(goal_reached)
    np.testing.assert_array_equal(script.label(pairs), [0.5, 0.5])
    # The distance at the end prefers trajectory 0, which began nearer; the gain prefers trajectory 1.
    np.testing.assert_array_equal(preference_source_from("progress", script).label(pairs), [1.0, 0.0])
    source = preference_source_from(spec, script)
    assert isinstance(source, ProgressTieBreaker) and source.measure == "gain"
    np.testing.assert_array_equal(source.label(pairs), [0.0, 1.0])
    with pytest.raises(ValueError, match="measure must be one of"):
        preference_source_from({"kind": "progress", "measure": "start"}, script)


def test_option_segments_are_consecutive_options_of_each_trajectory(buffer):
    pairs = pairs_of(buffer, [0] * 40 + [3], [2] * 40 + [1])
    pairs.labels[:] = 0.5
    segments = cut_option_segments(pairs, 2, np.random.default_rng(0))
    assert segments.mask.shape == (2, 41, 2) and segments.observations["achieved_goal"].shape == (2, 41, 2, 2)
    starts_seen = set()
    for side in (0, 1):
        for pair in range(41):
            # The start is the one whose two options the segment holds (trajectories 0, 2 and 1 have three options).
            start = int(
                np.flatnonzero(
                    np.all(
                        pairs.observations["achieved_goal"][side, pair]
                        == segments.observations["achieved_goal"][side, pair, 0],
                        axis=-1,
                    )
                )[0]
            )
            starts_seen.add(start)
            window = slice(start, start + 2)
            np.testing.assert_array_equal(
                segments.next_achieved_goals[side, pair], pairs.next_achieved_goals[side, pair, window]
            )
            np.testing.assert_array_equal(segments.actions[side, pair], pairs.actions[side, pair, window])
            np.testing.assert_array_equal(segments.reached_actions[side, pair], pairs.reached_actions[side, pair, window])
            np.testing.assert_array_equal(
                segments.observations["desired_goal"][side, pair], pairs.observations["desired_goal"][side, pair, window]
            )
    assert starts_seen == {0, 1}  # a three-option trajectory gives two windows of two, both drawn
    # Trajectory 3 has two options: its segment is all of it.
    np.testing.assert_array_equal(segments.mask[:, 40], [[True, True], [True, True]])
    np.testing.assert_allclose(segments.next_achieved_goals[0, 40], [[1, 1], [3, 0.1]], atol=1e-6)
    # One option longer than a trajectory: the segment keeps its options and masks the rest.
    whole = cut_option_segments(pairs_of(buffer, [3], [0]), 3, np.random.default_rng(1))
    np.testing.assert_array_equal(whole.mask[:, 0], [[True, True, False], [True, True, True]])
    assert np.isnan(whole.labels).all() and segments.labels.tolist() == [0.5] * 41


def test_the_sampler_cuts_segments_before_it_truncates_at_the_goal(buffer):
    sampler = TrajectoryPairSampler(0.0, SPACE, goal_reached=goal_reached, segment_options=2)
    assert sampler.pair_length == 2 and TrajectoryPairSampler(0.0, SPACE).pair_length is None
    pairs = sampler.sample(buffer, 200, np.random.default_rng(3))
    assert pairs.mask.shape == (2, 200, 2) and pairs.goal_driven.shape == (2, 200)
    # A segment that reaches GOAL (3, 0) at its first option ends both segments of its pair there.
    first_arrival = goal_reached(pairs.next_achieved_goals[:, :, 0], pairs.observations["desired_goal"][:, :, 0]).any(axis=0)
    assert first_arrival.any() and not pairs.mask[:, first_arrival, 1].any()


# A 3 x 3 maze of unit cells centred on the integer points, its middle row walled but for its right cell; the goal sits
# in the bottom-left cell (2, 0). Along the free cells, (0, 0) is 6 steps from it, (0, 1) 5, (0, 2) 4.
SMALL_MAZE = MazeGeometry(rows=3, cols=3, cell_size=1.0, origin=(0.0, 0.0), grip_height=0.0)
SMALL_GRID = np.array([[0, 0, 0], [1, 1, 0], [0, 0, 0]], dtype=np.float32)
MAZE_GOAL = np.array([2.0, 0.0], dtype=np.float32)


def maze_pairs(starts: list[tuple[float, float]], ends: list[tuple[float, float]]) -> TrajectoryPairs:
    """One pair of one-option trajectories on :data:`SMALL_MAZE`: ``starts[i]`` to ``ends[i]`` for tau^i."""
    points = np.array(starts, dtype=np.float32).reshape(2, 1, 1, 2)
    grid = np.broadcast_to(SMALL_GRID.ravel(), (2, 1, 1, 9))
    observations = {
        "observation": np.concatenate([points, np.zeros((2, 1, 1, 1), np.float32), grid], axis=-1),
        "achieved_goal": points,
        "desired_goal": np.broadcast_to(MAZE_GOAL, (2, 1, 1, 2)).copy(),
    }
    return TrajectoryPairs(
        observations=observations,
        actions=np.zeros((2, 1, 1, 2), np.float32),
        reached_actions=np.zeros((2, 1, 1, 2), np.float32),
        next_achieved_goals=np.array(ends, dtype=np.float32).reshape(2, 1, 1, 2),
        mask=np.ones((2, 1, 1), dtype=bool),
        labels=np.full(1, np.nan, dtype=np.float32),
    )


@pytest.mark.parametrize("spec", ["progress:path_gain", {"kind": "progress", "measure": "path_gain"}])
def test_the_path_gain_prefers_the_way_round_the_wall_to_pressing_against_it(spec):
    # tau^1 goes from (0, 0) to (0, 2), round toward the gate: 6 -> 4 steps along the free cells, though 2 -> 2.83 in
    # a straight line. tau^2 goes from (0, 2) to (0, 0), pressing against the wall nearest the goal: 4 -> 6 steps,
    # 2.83 -> 2 in a straight line. Neither reaches the goal, so the primitive-in-the-loop label is a tie.
    pairs = maze_pairs([(0, 0), (0, 2)], [(0, 2), (0, 0)])
    np.testing.assert_allclose(final_path_distances(pairs, SMALL_MAZE.path_distances), [[4.0], [6.0]])
    np.testing.assert_allclose(path_distance_gains(pairs, SMALL_MAZE.path_distances), [[2.0], [-2.0]])
    np.testing.assert_allclose(goal_distance_gains(pairs), [[2 - np.sqrt(8)], [np.sqrt(8) - 2]], atol=1e-6)
    script = PrimitiveInTheLoopLabeler(goal_reached)
    assert script.label(pairs).tolist() == [0.5]
    assert preference_source_from("progress:gain", script).label(pairs).tolist() == [0.0]  # the straight line: tau^2
    with pytest.raises(ValueError, match="has no maze geometry"):
        preference_source_from(spec, script)  # no env to take a maze from
    with pytest.raises(ValueError, match="needs path_distances"):
        ProgressTieBreaker(script, measure="path_gain").label(pairs)
    source = ProgressTieBreaker(script, measure="path_gain", path_distances=SMALL_MAZE.path_distances)
    assert source.label(pairs).tolist() == [1.0]  # along the free cells: tau^1
    assert source.label(maze_pairs([(0, 2), (0, 1)], [(0, 0), (0, 2)])).tolist() == [0.0]  # -2 against +1


def test_the_path_gain_needs_an_env_with_a_maze(maze_env):
    script = PrimitiveInTheLoopLabeler(goal_reached)
    with pytest.raises(
        ValueError, match=r"preference_source 'progress:path_gain' .*PointMazeFourRooms-v0.* has no maze geometry"
    ):
        preference_source_from("progress:path_gain", script, maze_env)


# ---------------------------------------------------------------------------------------------------- the pipeline


class QueueingLabeler(PreferenceSource):
    """Queues every other pair (NaN) for a person, who labels them 0.5 when :meth:`answer` is called."""

    def __init__(self) -> None:
        self.queued: TrajectoryPairs | None = None
        self.arrived: TrajectoryPairs | None = None
        self.restored_with: np.ndarray | None = None

    @property
    def pending(self) -> int:
        return 0 if self.queued is None else len(self.queued)

    def label(self, pairs: TrajectoryPairs) -> np.ndarray:
        labels = PrimitiveInTheLoopLabeler(goal_reached).label(pairs)
        labels[1::2] = np.nan
        self.queued = pairs.select(np.arange(1, len(pairs), 2))
        return labels

    def answer(self) -> None:
        self.arrived, self.queued = self.queued, None
        assert self.arrived is not None
        self.arrived.labels = np.full(len(self.arrived), 0.5, dtype=np.float32)

    def collect(self) -> TrajectoryPairs | None:
        arrived, self.arrived = self.arrived, None
        return arrived

    @property
    def handed_ids(self) -> np.ndarray:
        return np.array([7], dtype=np.int64)

    def dataset_restored(self, handed_ids: np.ndarray | None = None) -> None:
        self.restored_with = handed_ids


def pipeline_of(buffer: TrajectoryBuffer, labeler: PreferenceSource, budget: int = 100) -> PreferencePipeline:
    return PreferencePipeline(buffer, budget, TrajectoryPairSampler(0.5, SPACE), labeler)


def test_the_pipeline_labels_the_pairs_due_and_adds_late_labels_when_they_arrive(buffer):
    labeler = QueueingLabeler()
    pipeline = pipeline_of(buffer, labeler)
    new = pipeline.label_new_pairs(num_timesteps=10, total_timesteps=100, rng=np.random.default_rng(0))
    # A tenth of the budget is due; every other pair waits for its label.
    assert new is not None and len(new) == 10 and np.isnan(new.labels[1::2]).all()
    assert len(pipeline.dataset) == 5 and labeler.pending == 5
    # Pairs waiting for a person count as asked: none is due until training moves on.
    assert pipeline.label_new_pairs(num_timesteps=10, total_timesteps=100, rng=np.random.default_rng(1)) is None
    labeler.answer()
    # The answers join first, then the rest of the share is labelled (one of the two new pairs queued).
    new = pipeline.label_new_pairs(num_timesteps=12, total_timesteps=100, rng=np.random.default_rng(2))
    assert new is not None and len(new) == 2 and len(pipeline.dataset) == 11
    assert pipeline.dataset.handed_ids.tolist() == [7]


def test_the_pipeline_waits_for_enough_trajectories():
    buffer = TrajectoryBuffer(capacity=4, max_length=3, observation_space=OBS_SPACE, action_dim=2)
    add_trajectory(buffer, [(1, 0)])
    pipeline = pipeline_of(buffer, PrimitiveInTheLoopLabeler(goal_reached))
    assert pipeline.label_new_pairs(50, 100, np.random.default_rng(0)) is None  # whole-trajectory pairs need two
    segments = PreferencePipeline(buffer, 100, SegmentPairSampler(1, 0.5), PrimitiveInTheLoopLabeler(goal_reached))
    assert len(segments.label_new_pairs(50, 100, np.random.default_rng(0))) == 50


def test_the_pipeline_truncates_at_the_first_arrival_when_asked(buffer):
    sampler = TrajectoryPairSampler(0.0, SPACE, goal_reached)
    whole = TrajectoryPairSampler(0.0, SPACE).sample(buffer, 50, np.random.default_rng(3))
    truncated = sampler.sample(buffer, 50, np.random.default_rng(3))
    np.testing.assert_array_equal(truncated.mask, truncate_at_first_arrival(whole, goal_reached).mask)
    assert truncated.mask.sum() < whole.mask.sum()


def test_the_pipeline_saves_and_restores_itself_all_or_nothing(buffer, tmp_path):
    labeler = QueueingLabeler()
    pipeline = pipeline_of(buffer, labeler)
    pipeline.label_new_pairs(10, 100, np.random.default_rng(0))
    labeler.answer()
    pipeline.label_new_pairs(12, 100, np.random.default_rng(1))
    pipeline.save(tmp_path / "high.npz")

    fresh_buffer = TrajectoryBuffer(capacity=10, max_length=3, observation_space=OBS_SPACE, action_dim=2)
    restored_labeler = QueueingLabeler()
    restored = pipeline_of(fresh_buffer, restored_labeler)
    install = restored.read(tmp_path / "high.npz")
    assert len(fresh_buffer) == 0 and len(restored.dataset) == 0 and restored_labeler.restored_with is None
    install()
    assert len(fresh_buffer) == len(buffer) and restored_labeler.restored_with.tolist() == [7]
    np.testing.assert_array_equal(restored.dataset.all_pairs().labels, pipeline.dataset.all_pairs().labels)
    # The file is the one save_preference_data writes.
    restored_dataset = load_preference_data(tmp_path / "high.npz", fresh_buffer, label_budget=100)
    np.testing.assert_array_equal(restored_dataset.all_pairs().labels, pipeline.dataset.all_pairs().labels)

    smaller = TrajectoryBuffer(capacity=5, max_length=3, observation_space=OBS_SPACE, action_dim=2)
    untouched = pipeline_of(smaller, QueueingLabeler())
    with pytest.raises(ValueError, match="trajectory_buffer_size=10"):
        untouched.load(tmp_path / "high.npz")
    assert len(smaller) == 0 and len(untouched.dataset) == 0


# ------------------------------------------------------------------------------------------ option segments in DIPPER


def test_dipper_labels_option_segments_by_the_path_gain_along_its_mazes_free_cells():
    env = make_vec_env("FetchFourRoomMaze-v0", n_envs=1, seed=0, env_kwargs=dict(max_episode_steps=30))
    model = tiny_model(DIPPER, env, segment_options=2, preference_source="progress:path_gain", n_preference_pairs=40)
    maze = env.get_attr("maze")[0]
    assert model.preference_pipeline.labeler.path_distances == maze.path_distances  # bound to the env's maze
    model.learn(300)
    pairs = model.preferences.all_pairs()
    assert pairs is not None and len(pairs) > 0 and pairs.mask.shape[-1] == 2
    # Where no segment reached the goal, the label is the path-gain oracle's.
    reached = PrimitiveInTheLoopLabeler(model._goal_reached).scores(pairs)
    untouched = (reached == 0).all(axis=0)
    expected = labels_from_scores(path_distance_gains(pairs.select(np.flatnonzero(untouched)), maze.path_distances))
    np.testing.assert_array_equal(pairs.labels[untouched], expected)
    with pytest.raises(ValueError, match=r"segment_options=7 is longer than a higher-level trajectory \(6 options\)"):
        tiny_model(DIPPER, env, segment_options=7)
