"""Preference pairs over higher-level trajectories: sampling, labelling and the stored dataset.

Pair sampling follows the authors' PIPER code: two whole trajectories are drawn from the trajectory buffer and, with
probability ``hindsight_goal_prob``, both are relabelled with one shared goal, an achieved goal taken from one of
them, so that both answer the same "prompt". Labels come from a :class:`PreferenceSource`; the default is the
primitive-in-the-loop labeller of the DIPPER paper (Section 4.3), which scores a trajectory by the number of options
that ended within the goal threshold, ``R(tau) = sum_t 1[ag_{t+1} reached g]``, and prefers the higher score
(ties are labelled 0.5). The score depends only on reached states, not on the lower policy's behaviour, so labelled
pairs stay valid for the whole run: the dataset is stationary.

A labelled pair is stored whole (observations, actions, reached subgoals), so the dataset does not depend on the
trajectory buffer, is saved as npz (read without pickle), and can be replaced by labels from people.
"""

from __future__ import annotations

import warnings
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from sb3_dipper.common.files import read_npz, save_npz
from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.common.trajectories import TrajectoryBuffer
from sb3_dipper.common.validation import GOAL_KEYS

# Label at most this many new pairs per training round, so labelling never stalls a round.
MAX_NEW_PAIRS_PER_ROUND = 256

DictObs = dict[str, np.ndarray]
# What a sampler records of how it drew pairs (:class:`TrajectoryPairs`): diagnostics, not kept in a dataset or file.
SAMPLER_RECORDS = ("goal_driven", "shared_goal")
GoalReachedFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
# ``path_distances(observations, points, goals) -> (N,)``: how far each point lies from its goal along the free space
# the observation describes (a maze's free cells), for observations ``(N, obs_dim)`` and points and goals ``(N, goal_dim)``.
PathDistanceFn = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


@dataclass
class TrajectoryPairs:
    """A batch of trajectory pairs; index 0 of the leading pair axis is tau^1, index 1 is tau^2.

    Shapes: observations ``(2, B, T, ...)`` (``desired_goal`` holds the pair's goal), actions and reached_actions
    ``(2, B, T, d)``, next_achieved_goals ``(2, B, T, goal_dim)``, mask ``(2, B, T)``, labels ``(B,)`` (1: tau^1
    preferred, 0: tau^2 preferred, 0.5: tie).

    Where the pairs were drawn from a trajectory buffer, the sampler also says how: ``goal_driven`` ``(2, B)`` (the
    trajectory's every subgoal was the env's goal) and ``shared_goal`` ``(B,)`` (both trajectories were given one
    hindsight goal); ``None`` where that is not known (pairs from a file or a person). Datasets do not keep them.
    """

    observations: DictObs
    actions: np.ndarray
    reached_actions: np.ndarray
    next_achieved_goals: np.ndarray
    mask: np.ndarray
    labels: np.ndarray
    goal_driven: np.ndarray | None = None
    shared_goal: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    def select(self, indices: np.ndarray) -> TrajectoryPairs:
        return TrajectoryPairs(
            observations={key: value[:, indices] for key, value in self.observations.items()},
            actions=self.actions[:, indices],
            reached_actions=self.reached_actions[:, indices],
            next_achieved_goals=self.next_achieved_goals[:, indices],
            mask=self.mask[:, indices],
            labels=self.labels[indices],
            goal_driven=None if self.goal_driven is None else self.goal_driven[:, indices],
            shared_goal=None if self.shared_goal is None else self.shared_goal[indices],
        )


def relabel_hindsight_actions(next_achieved_goals: np.ndarray, subgoal_space: SubgoalSpace) -> np.ndarray:
    """The higher-level action that would have proposed what the option reached (HAC's hindsight action).

    It does not depend on how well the lower level followed the proposed subgoal, and it is feasible by construction.
    """
    return subgoal_space.to_unit(subgoal_space.project(next_achieved_goals))


def trajectory_starts(observations: DictObs) -> np.ndarray:
    """Where trajectories started: the achieved goal and the goal at the first step, side by side (``(..., 2 *
    goal_dim)`` from observations ``(..., T, goal_dim)``), what matching starts in goal coordinates compares."""
    return np.concatenate([observations["achieved_goal"][..., 0, :], observations["desired_goal"][..., 0, :]], axis=-1)


def match_control_trajectories(
    buffer: TrajectoryBuffer, n_pairs: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray] | None:
    """``n_pairs`` stored trajectories not driven by the goal, drawn uniformly, each with the goal-driven trajectory
    (:attr:`~sb3_dipper.common.trajectories.TrajectoryBuffer.goal_driven`) whose start is nearest
    (:func:`trajectory_starts`, Euclidean), as two index arrays; ``None`` when the buffer lacks either kind.

    The pair then compares the policy's subgoals with the goal-driven control's from about the same start toward about
    the same goal, where two trajectories drawn at random on a task with random starts and goals start apart.
    """
    stored = np.arange(len(buffer))
    driven = buffer.goal_driven[: len(buffer)]
    controls, own = stored[driven], stored[~driven]
    if len(controls) == 0 or len(own) == 0:
        return None
    policy_rows = rng.choice(own, size=n_pairs)
    starts = trajectory_starts({key: buffer.observations[key][: len(buffer)] for key in ("achieved_goal", "desired_goal")})
    gaps = np.linalg.norm(starts[policy_rows, None] - starts[None, controls], axis=-1)
    return policy_rows, controls[gaps.argmin(axis=1)]


def twin_control_trajectories(
    buffer: TrajectoryBuffer, n_pairs: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray] | None:
    """``n_pairs`` stored trajectories not driven by the goal, drawn uniformly among those whose episode a stored
    goal-driven trajectory replayed (the same :attr:`~sb3_dipper.common.trajectories.TrajectoryBuffer.episode_seeds`:
    twin episodes), each with that twin, as two index arrays; ``None`` when no stored trajectory has a twin.

    The pair then compares the policy's subgoals with the goal as every subgoal in the same episode: same layout, same
    start, same goal.
    """
    stored = np.arange(len(buffer))
    seeds = buffer.episode_seeds[: len(buffer)]
    driven = buffer.goal_driven[: len(buffer)]
    known = seeds >= 0
    controls = stored[driven & known]
    # One control per seed: a seed is drawn from 2**62 values, so it names one episode (of a stored pair, the later row).
    control_of_seed = dict(zip(seeds[controls].tolist(), controls.tolist(), strict=True))
    own = stored[~driven & known]
    twinned = own[np.isin(seeds[own], seeds[controls])]
    if len(twinned) == 0:
        return None
    policy_rows = rng.choice(twinned, size=n_pairs)
    return policy_rows, np.array([control_of_seed[seed] for seed in seeds[policy_rows].tolist()], dtype=np.int64)


def start_gaps(pairs: TrajectoryPairs) -> np.ndarray:
    """``(B,)``: how far apart the two trajectories of each pair started (:func:`trajectory_starts`, Euclidean; with the
    pair's goals, hindsight goals included)."""
    starts = trajectory_starts(pairs.observations)
    return np.linalg.norm(starts[0] - starts[1], axis=-1)


def sample_trajectory_pairs(
    buffer: TrajectoryBuffer,
    n_pairs: int,
    hindsight_goal_prob: float,
    subgoal_space: SubgoalSpace,
    rng: np.random.Generator,
    contrast_env_goals: bool = True,
    matched_control_prob: float = 0.0,
    match_twins: bool = False,
) -> TrajectoryPairs:
    """Draw ``n_pairs`` unlabelled pairs; with ``hindsight_goal_prob`` both share a goal achieved by one of them, except,
    with ``contrast_env_goals``, a pair of a goal-driven trajectory
    (:attr:`~sb3_dipper.common.trajectories.TrajectoryBuffer.goal_driven`) and another, which compares the control with
    the other driver on the env's own goals (the draws are the same either way). With ``matched_control_prob`` a pair
    is instead a trajectory of the policy's (tau^1) and the goal-driven one that started nearest it (tau^2,
    :func:`match_control_trajectories`), or with ``match_twins`` the goal-driven one that played the same episode
    (:func:`twin_control_trajectories`); at 0 no draw is made for it, so the pairs are those drawn without it."""
    if len(buffer) < 2:
        raise ValueError("Preference pairs need at least two finished higher-level trajectories")
    indices = rng.integers(len(buffer), size=(2, n_pairs))
    if matched_control_prob > 0.0:
        matched = rng.random(n_pairs) < matched_control_prob
        match = twin_control_trajectories if match_twins else match_control_trajectories
        matches = match(buffer, int(matched.sum()), rng)
        if matches is not None:
            indices[:, matched] = np.stack(matches)
    observations = {key: value[indices].copy() for key, value in buffer.observations.items()}
    next_achieved_goals = buffer.next_achieved_goals[indices]
    mask = np.stack([buffer.mask(indices[0]), buffer.mask(indices[1])])

    contrast = (buffer.goal_driven[indices[0]] != buffer.goal_driven[indices[1]]) & contrast_env_goals
    share_goal = (rng.random(n_pairs) < hindsight_goal_prob) & ~contrast
    source = rng.integers(2, size=n_pairs)
    lengths = buffer.lengths[indices[source, np.arange(n_pairs)]]
    step = (rng.random(n_pairs) * lengths).astype(np.int64)
    hindsight_goals = next_achieved_goals[source, np.arange(n_pairs), step]
    goals = observations["desired_goal"]
    goals[:, share_goal] = hindsight_goals[None, share_goal, None, :]

    return TrajectoryPairs(
        observations=observations,
        actions=buffer.actions[indices],
        reached_actions=relabel_hindsight_actions(next_achieved_goals, subgoal_space),
        next_achieved_goals=next_achieved_goals,
        mask=mask,
        labels=np.full(n_pairs, np.nan, dtype=np.float32),
        goal_driven=buffer.goal_driven[indices],
        shared_goal=share_goal,
    )


def sample_segment_pairs(
    buffer: TrajectoryBuffer,
    n_pairs: int,
    segment_length: int,
    hindsight_goal_prob: float,
    rng: np.random.Generator,
) -> TrajectoryPairs:
    """``n_pairs`` unlabelled pairs of segments of ``segment_length`` consecutive steps, each cut from a stored episode.

    A segment starts uniformly where it fits in its episode (an episode shorter than ``segment_length`` gives a shorter,
    masked segment). With ``hindsight_goal_prob`` both segments of a pair get one goal, the achieved goal after a random
    step of one of them; otherwise each keeps its own goal. Primitive actions have no hindsight counterpart, so
    ``reached_actions`` are the actions.
    """
    if len(buffer) < 1:
        raise ValueError("Segment pairs need at least one finished episode in the trajectory buffer")
    episodes = rng.integers(len(buffer), size=(2, n_pairs))
    lengths = buffer.lengths[episodes]
    starts = (rng.random((2, n_pairs)) * (np.maximum(lengths - segment_length, 0) + 1)).astype(np.int64)
    steps = starts[..., None] + np.arange(segment_length)
    mask = steps < lengths[..., None]
    steps = np.minimum(steps, buffer.max_length - 1)
    rows = episodes[..., None]
    observations = {key: value[rows, steps] for key, value in buffer.observations.items()}
    next_achieved_goals = buffer.next_achieved_goals[rows, steps]

    pair_index = np.arange(n_pairs)
    share_goal = rng.random(n_pairs) < hindsight_goal_prob
    source = rng.integers(2, size=n_pairs)
    step = (rng.random(n_pairs) * mask[source, pair_index].sum(axis=-1)).astype(np.int64)
    hindsight_goals = next_achieved_goals[source, pair_index, step]
    observations["desired_goal"][:, share_goal] = hindsight_goals[None, share_goal, None, :]

    actions = buffer.actions[rows, steps]
    return TrajectoryPairs(
        observations=observations,
        actions=actions,
        reached_actions=actions,
        next_achieved_goals=next_achieved_goals,
        mask=mask,
        labels=np.full(n_pairs, np.nan, dtype=np.float32),
        shared_goal=share_goal,
    )


def cut_option_segments(pairs: TrajectoryPairs, length: int, rng: np.random.Generator) -> TrajectoryPairs:
    """Each trajectory of each pair cut to ``length`` consecutive options, starting uniformly where they fit in it (a
    trajectory of fewer options keeps them all, masked to ``length``); the pair keeps its goal.

    A label of two whole trajectories tells which one ended better, not which of its subgoals did it; a label of two
    segments of one or two options credits the subgoals that made the difference.
    """
    lengths = pairs.mask.sum(axis=-1)
    starts = (rng.random(lengths.shape) * (np.maximum(lengths - length, 0) + 1)).astype(np.int64)
    steps = starts[..., None] + np.arange(length)
    mask = steps < lengths[..., None]
    steps = np.minimum(steps, pairs.mask.shape[-1] - 1)

    def cut(values: np.ndarray) -> np.ndarray:
        index = steps.reshape(*steps.shape, *([1] * (values.ndim - 3)))
        return np.take_along_axis(values, index, axis=2)

    return TrajectoryPairs(
        observations={key: cut(value) for key, value in pairs.observations.items()},
        actions=cut(pairs.actions),
        reached_actions=cut(pairs.reached_actions),
        next_achieved_goals=cut(pairs.next_achieved_goals),
        mask=mask & cut(pairs.mask),
        labels=pairs.labels,
        goal_driven=pairs.goal_driven,
        shared_goal=pairs.shared_goal,
    )


def truncate_at_first_arrival(pairs: TrajectoryPairs, goal_reached: GoalReachedFn) -> TrajectoryPairs:
    """End both trajectories of a pair at the first option after which either of them reached the pair's goal.

    The primitive-in-the-loop score of the truncated pair prefers the trajectory that arrived first (a tie when both
    arrive together or neither arrives). Without truncation, a trajectory that passed its hindsight goal early is
    preferred for all its later options too, although those were not steering toward that goal.
    """
    reached = goal_reached(pairs.next_achieved_goals, pairs.observations["desired_goal"]) & pairs.mask
    either_reached = reached.any(axis=0)
    horizon = pairs.mask.shape[-1]
    first_arrival = np.where(either_reached.any(axis=-1), either_reached.argmax(axis=-1), horizon - 1)
    keep = np.arange(horizon)[None, :] <= first_arrival[:, None]
    return TrajectoryPairs(
        observations=pairs.observations,
        actions=pairs.actions,
        reached_actions=pairs.reached_actions,
        next_achieved_goals=pairs.next_achieved_goals,
        mask=pairs.mask & keep[None],
        labels=pairs.labels,
        goal_driven=pairs.goal_driven,
        shared_goal=pairs.shared_goal,
    )


class PairSampler(ABC):
    """Draws the unlabelled pairs an algorithm has labelled, from its trajectory buffer."""

    #: the fewest finished trajectories (or episodes) in the buffer it draws pairs from
    min_trajectories: int = 1
    #: T, the steps of each trajectory of a pair (``None``: whole trajectories, the buffer's ``max_length``)
    pair_length: int | None = None

    @abstractmethod
    def sample(self, buffer: TrajectoryBuffer, n_pairs: int, rng: np.random.Generator) -> TrajectoryPairs:
        """``n_pairs`` unlabelled pairs (labels NaN) drawn from ``buffer`` with ``rng``."""


class TrajectoryPairSampler(PairSampler):
    """Pairs of whole higher-level trajectories (:func:`sample_trajectory_pairs`, PIPER's pairs), optionally ended at
    the first arrival at the goal (:func:`truncate_at_first_arrival`).

    :param hindsight_goal_prob: probability that both trajectories of a pair share a goal achieved by one of them
    :param subgoal_space: the higher level's subgoal space (for the hindsight actions)
    :param goal_reached: end each pair when the first of its trajectories reaches the goal, as this tells (``None``:
        whole trajectories)
    :param contrast_env_goals: a pair of a goal-driven trajectory and another keeps the env's goals
    :param matched_control_prob: probability that a pair is a trajectory of the policy's and the goal-driven one that
        started nearest it
    :param match_twins: the goal-driven one of a matched pair is instead the one that played the same episode
    :param segment_options: cut each trajectory of a pair to this many consecutive options
        (:func:`cut_option_segments`), before the truncation at the goal (``None``: whole trajectories)
    """

    min_trajectories = 2

    def __init__(
        self,
        hindsight_goal_prob: float,
        subgoal_space: SubgoalSpace,
        goal_reached: GoalReachedFn | None = None,
        contrast_env_goals: bool = True,
        matched_control_prob: float = 0.0,
        match_twins: bool = False,
        segment_options: int | None = None,
    ) -> None:
        self.pair_length = segment_options
        self.hindsight_goal_prob = hindsight_goal_prob
        self.subgoal_space = subgoal_space
        self.goal_reached = goal_reached
        self.contrast_env_goals = contrast_env_goals
        self.matched_control_prob = matched_control_prob
        self.match_twins = match_twins

    def sample(self, buffer: TrajectoryBuffer, n_pairs: int, rng: np.random.Generator) -> TrajectoryPairs:
        pairs = sample_trajectory_pairs(
            buffer,
            n_pairs,
            self.hindsight_goal_prob,
            self.subgoal_space,
            rng,
            self.contrast_env_goals,
            self.matched_control_prob,
            self.match_twins,
        )
        if self.pair_length is not None:
            pairs = cut_option_segments(pairs, self.pair_length, rng)
        return pairs if self.goal_reached is None else truncate_at_first_arrival(pairs, self.goal_reached)


class SegmentPairSampler(PairSampler):
    """Pairs of segments of ``segment_length`` primitive steps cut from stored episodes (:func:`sample_segment_pairs`,
    DPO-FLAT's pairs).

    :param segment_length: primitive steps per segment
    :param hindsight_goal_prob: probability that both segments of a pair share a goal achieved by one of them
    """

    min_trajectories = 1

    def __init__(self, segment_length: int, hindsight_goal_prob: float) -> None:
        self.segment_length = segment_length
        self.hindsight_goal_prob = hindsight_goal_prob
        self.pair_length = segment_length

    def sample(self, buffer: TrajectoryBuffer, n_pairs: int, rng: np.random.Generator) -> TrajectoryPairs:
        return sample_segment_pairs(buffer, n_pairs, self.segment_length, self.hindsight_goal_prob, rng)


def labels_from_scores(scores: np.ndarray) -> np.ndarray:
    """``(2, B)`` scores to labels: 1 if tau^1 scores higher, 0 if lower, 0.5 on ties."""
    return np.where(scores[0] > scores[1], 1.0, np.where(scores[0] < scores[1], 0.0, 0.5)).astype(np.float32)


def last_options(pairs: TrajectoryPairs) -> tuple[DictObs, np.ndarray]:
    """Each trajectory's last real option: its observation (every key, ``desired_goal`` the pair's goal) and the
    achieved goal it reached, ``(2, B, ...)`` each."""
    last = np.maximum(pairs.mask.sum(axis=-1) - 1, 0)

    def at_last(values: np.ndarray) -> np.ndarray:
        index = last.reshape(*last.shape, 1, *([1] * (values.ndim - 3)))
        return np.take_along_axis(values, index, axis=2)[:, :, 0]

    return {key: at_last(value) for key, value in pairs.observations.items()}, at_last(pairs.next_achieved_goals)


def final_goal_distances(pairs: TrajectoryPairs) -> np.ndarray:
    """``(2, B)``: the distance from where each trajectory's last real option ended to the pair's goal (Euclidean,
    in goal coordinates): the progress an oracle that knows the task's geometry would compare."""
    observations, reached = last_options(pairs)
    return np.linalg.norm(reached - observations["desired_goal"], axis=-1)


def progress_labels(pairs: TrajectoryPairs) -> np.ndarray:
    """Labels of an oracle that knows the true progress: the trajectory that ends nearer the goal is preferred."""
    return labels_from_scores(-final_goal_distances(pairs))


def policy_preferred_share(pairs: TrajectoryPairs) -> float | None:
    """Over the labelled pairs of a goal-driven trajectory and one that is not (``pairs.goal_driven``), how much the
    labels prefer the one that is not, the policy's (a tie counts half); ``None`` where there is no such pair. Above
    0.5 the policy's subgoals beat the goal's more often than not."""
    if pairs.goal_driven is None:
        return None
    contrast = pairs.goal_driven[0] != pairs.goal_driven[1]
    if not contrast.any():
        return None
    policy_first = ~pairs.goal_driven[0, contrast]
    labels = pairs.labels[contrast]
    return float(np.mean(np.where(policy_first, labels, 1.0 - labels)))


def start_goal_distances(pairs: TrajectoryPairs) -> np.ndarray:
    """``(2, B)``: each trajectory's distance from its goal at its first step (Euclidean, in goal coordinates)."""
    first = pairs.observations
    return np.linalg.norm(first["achieved_goal"][:, :, 0] - first["desired_goal"][:, :, 0], axis=-1)


def goal_distance_gains(pairs: TrajectoryPairs) -> np.ndarray:
    """``(2, B)``: how much nearer the pair's goal each trajectory ended than it started
    (:func:`start_goal_distances` minus :func:`final_goal_distances`). Where the two trajectories of a pair start apart
    (tasks with random starts and goals), the distance at the end favours the one that began nearer its goal; the gain
    does not."""
    return start_goal_distances(pairs) - final_goal_distances(pairs)


def progress_gain_labels(pairs: TrajectoryPairs) -> np.ndarray:
    """Labels of an oracle of the progress each trajectory made: the one whose distance to the goal fell more wins."""
    return labels_from_scores(goal_distance_gains(pairs))


def _path_distances_at(observations: DictObs, points: np.ndarray, path_distances: PathDistanceFn) -> np.ndarray:
    """``(2, B)``: ``path_distances`` of ``points`` ``(2, B, goal_dim)`` from the pair's goals, in the free space that
    ``observations`` (one step of each trajectory, ``(2, B, ...)``) describe."""
    states, goals = observations["observation"], observations["desired_goal"]
    distances = path_distances(
        states.reshape(-1, states.shape[-1]), points.reshape(-1, points.shape[-1]), goals.reshape(-1, goals.shape[-1])
    )
    return np.asarray(distances, dtype=np.float64).reshape(points.shape[:2])


def final_path_distances(pairs: TrajectoryPairs, path_distances: PathDistanceFn) -> np.ndarray:
    """``(2, B)``: how far each trajectory's last real option ended from the pair's goal along the free space
    (``path_distances``, e.g. a maze's :meth:`~sb3_dipper.envs.fetch.MazeGeometry.path_distances`)."""
    observations, reached = last_options(pairs)
    return _path_distances_at(observations, reached, path_distances)


def path_distance_gains(pairs: TrajectoryPairs, path_distances: PathDistanceFn) -> np.ndarray:
    """``(2, B)``: how much nearer the pair's goal along the free space each trajectory ended than it started. Where
    walls stand between a trajectory and its goal, the straight distance rewards pressing against the wall nearest the
    goal; the distance along the free cells rewards the way round it."""
    first = {key: value[:, :, 0] for key, value in pairs.observations.items()}
    start = _path_distances_at(first, first["achieved_goal"], path_distances)
    return start - final_path_distances(pairs, path_distances)


class PreferenceSource(ABC):
    """Gives preference labels to trajectory pairs (a scripted labeller, an oracle, people).

    A synchronous source labels every pair in :meth:`label`. An asynchronous one (people) may instead queue a pair,
    answer NaN for it, and hand the pair back labelled from a later :meth:`collect`; until then it counts in
    :attr:`pending`. Training never waits for it: labelled pairs join the dataset, queued ones when they arrive.
    """

    @abstractmethod
    def label(self, pairs: TrajectoryPairs) -> np.ndarray:
        """Labels in {0, 0.5, 1} for each pair (1: the first trajectory is preferred), NaN for a pair left queued."""

    @property
    def pending(self) -> int:
        """Pairs queued by :meth:`label` whose label has not arrived yet (they count against the label budget)."""
        return 0

    def collect(self) -> TrajectoryPairs | None:
        """Queued pairs whose labels arrived since the last call, labelled (``None``: none)."""
        return None

    @property
    def handed_ids(self) -> np.ndarray:
        """The ids of the pairs :meth:`collect` handed to training, in order (saved with the dataset)."""
        return np.zeros(0, dtype=np.int64)  # a synchronous source hands nothing late

    def dataset_restored(self, handed_ids: np.ndarray | None = None) -> None:
        """The model's dataset was just restored from its saved file (``load_replay_buffer``): the pairs this source
        handed to training before that save are in it already, so :meth:`collect` must not hand them again; those
        handed after it are not, so :meth:`collect` hands them again.

        :param handed_ids: the dataset's record of the pairs handed to it (:attr:`PreferenceDataset.handed_ids`);
            ``None`` for a file saved before datasets kept that record
        """
        return None  # a synchronous source hands nothing late, so nothing twice


def add_new_labels(dataset: PreferenceDataset, source: PreferenceSource, pairs: TrajectoryPairs | None) -> None:
    """Add the pairs ``source`` labelled since the last call, then those of ``pairs`` it labelled now (NaN: queued)."""
    arrived = source.collect()
    if arrived is not None:
        dataset.add(arrived)
    dataset.handed_ids = source.handed_ids
    if pairs is not None:
        dataset.add(pairs.select(np.flatnonzero(~np.isnan(pairs.labels))))


class PrimitiveInTheLoopLabeler(PreferenceSource):
    """Primitive-in-the-loop labels (DIPPER paper, Section 4.3): count options that ended at the goal.

    :param goal_reached: ``goal_reached(achieved_goals, desired_goals)``, vectorised, True where the goal is reached
    :param value_score: optional ``value_score(pairs) -> (2, B)`` added to the score (PIPER's lower-value term)
    """

    def __init__(self, goal_reached: GoalReachedFn, value_score: Callable[[TrajectoryPairs], np.ndarray] | None = None):
        self.goal_reached = goal_reached
        self.value_score = value_score

    def scores(self, pairs: TrajectoryPairs) -> np.ndarray:
        reached = self.goal_reached(pairs.next_achieved_goals, pairs.observations["desired_goal"])
        scores = (reached.astype(np.float64) * pairs.mask).sum(axis=-1)
        if self.value_score is not None:
            scores = scores + self.value_score(pairs)
        return scores

    def label(self, pairs: TrajectoryPairs) -> np.ndarray:
        return labels_from_scores(self.scores(pairs))


class PreferenceDataset:
    """The labelled pairs D, filled up to a label budget; saved and loaded as npz without pickle.

    :attr:`handed_ids` records which pairs a source that labels late (people) handed to the dataset, so a dataset
    restored from a checkpoint tells the source which labels it holds and which, given after the save, it lacks.

    :param capacity: the label budget (most pairs ever stored)
    """

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"The preference dataset needs room for at least one pair, got capacity {capacity}")
        self.capacity = capacity
        self._pairs: TrajectoryPairs | None = None
        self.size = 0
        # None: not recorded (a file saved before the record existed).
        self.handed_ids: np.ndarray | None = None

    def __len__(self) -> int:
        return self.size

    @property
    def remaining(self) -> int:
        return self.capacity - self.size

    def add(self, pairs: TrajectoryPairs) -> None:
        if np.any(np.isnan(pairs.labels)):
            raise ValueError("Only labelled pairs can be added to the preference dataset")
        n_new = min(len(pairs), self.remaining)
        if n_new == 0:
            return
        if self._pairs is None:
            self._pairs = _allocate_like(pairs, self.capacity)
        stored = self._pairs
        for field in fields(TrajectoryPairs):
            if field.name in SAMPLER_RECORDS:
                continue
            new_value = getattr(pairs, field.name)
            if isinstance(new_value, dict):
                for key, array in new_value.items():
                    _write(stored.observations[key], array, self.size, n_new)
            else:
                _write(getattr(stored, field.name), new_value, self.size, n_new)
        self.size += n_new

    def sample(self, batch_size: int, rng: np.random.Generator) -> TrajectoryPairs:
        if self._pairs is None or self.size == 0:
            raise ValueError("The preference dataset is empty")
        return self._pairs.select(rng.integers(self.size, size=batch_size))

    def all_pairs(self) -> TrajectoryPairs | None:
        return None if self._pairs is None else self._pairs.select(np.arange(self.size))

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The labelled pairs as named arrays (the npz schema of :meth:`load`)."""
        arrays: dict[str, np.ndarray] = {"capacity": np.array(self.capacity)}
        if self.handed_ids is not None:
            arrays["handed_pair_ids"] = np.asarray(self.handed_ids, dtype=np.int64)
        pairs = self.all_pairs()
        if pairs is not None:
            arrays.update({f"observations/{key}": value for key, value in pairs.observations.items()})
            arrays.update(
                actions=pairs.actions,
                reached_actions=pairs.reached_actions,
                next_achieved_goals=pairs.next_achieved_goals,
                mask=pairs.mask,
                labels=pairs.labels,
            )
        return arrays

    def save(self, path: str | Path) -> None:
        """Write the labelled pairs to an npz file (schema: see :meth:`load`), atomically."""
        save_npz(path, self.to_arrays())

    @classmethod
    def load(cls, path: str | Path, capacity: int | None = None, shapes: PairShapes | None = None) -> PreferenceDataset:
        """Read a preference file written by :meth:`save` (or by hand, following the same schema).

        Schema: ``labels (N,)`` in {0, 0.5, 1}; ``mask (2, N, T)``; ``actions``, ``reached_actions`` ``(2, N, T, d)``;
        ``next_achieved_goals (2, N, T, goal_dim)``; ``observations/<key> (2, N, T, ...)`` for every observation key
        (at least ``observation``, ``achieved_goal`` and ``desired_goal``, which holds the pair's goal); optional
        ``capacity`` (the label budget) and ``handed_pair_ids`` (:attr:`handed_ids`). Values must be finite.

        :param path: the npz file
        :param capacity: the label budget (default: the file's); pairs beyond it are dropped, with a warning
        :param shapes: the model's pair shapes (:meth:`PairShapes.of`), to check the file against
        """
        arrays = read_npz(path, "preference file")
        return cls.from_arrays(arrays, capacity, str(path), shapes)

    @classmethod
    def from_arrays(
        cls,
        arrays: dict[str, np.ndarray],
        capacity: int | None = None,
        source: str = "arrays",
        shapes: PairShapes | None = None,
        capacity_name: str = "capacity",
    ) -> PreferenceDataset:
        """Build a dataset from :meth:`to_arrays` output, checking every array (and, given ``shapes``, the model's).

        :param arrays: the named arrays
        :param capacity: the label budget (default: the stored one); pairs beyond it are dropped, with a warning
        :param source: where the arrays come from, for messages
        :param shapes: the shapes the pairs must have
        :param capacity_name: the parameter that sets ``capacity``, named in the warning about dropped pairs
        """
        arrays = dict(arrays)
        stored_capacity = arrays.pop("capacity", np.array(0))
        if stored_capacity.shape != () or stored_capacity.dtype.kind not in "iu" or stored_capacity < 0:
            raise ValueError(f"Malformed preference file {source}: capacity must be one integer >= 0, got {stored_capacity}")
        handed_ids = arrays.pop("handed_pair_ids", None)
        if handed_ids is not None and (handed_ids.ndim != 1 or handed_ids.dtype.kind not in "iu"):
            raise ValueError(f"Malformed preference file {source}: handed_pair_ids must be a vector of integers")
        if not arrays:
            dataset = cls(capacity or max(int(stored_capacity), 1))
            dataset.handed_ids = handed_ids
            return dataset
        pairs = pairs_from_arrays(arrays, source, shapes)
        dataset = cls(capacity or max(int(stored_capacity), len(pairs)))
        dataset.handed_ids = handed_ids
        if len(pairs) > dataset.capacity:
            warnings.warn(
                f"{source} holds {len(pairs)} labelled pairs but {capacity_name}={dataset.capacity}: kept the first "
                f"{dataset.capacity} and dropped {len(pairs) - dataset.capacity}. Raise {capacity_name} to "
                f"{len(pairs)} or more to keep them all."
            )
        dataset.add(pairs)
        return dataset


@dataclass(frozen=True)
class PairShapes:
    """What every step of a model's pairs looks like, to check pairs read from a file against the model.

    :param observations: the shape of each observation key (one step)
    :param action_dim: d, the size of ``actions`` and ``reached_actions``
    :param length: T, the steps of each trajectory (or segment) of a pair
    """

    observations: dict[str, tuple[int, ...]]
    action_dim: int
    length: int

    @classmethod
    def of(cls, trajectory_buffer: TrajectoryBuffer, length: int | None = None) -> PairShapes:
        """The pairs cut from ``trajectory_buffer``: whole trajectories, or segments of ``length`` steps."""
        return cls(
            observations={key: value.shape[2:] for key, value in trajectory_buffer.observations.items()},
            action_dim=int(trajectory_buffer.actions.shape[-1]),
            length=length or trajectory_buffer.max_length,
        )


def pairs_due(
    dataset: PreferenceDataset, label_budget: int, num_timesteps: int, total_timesteps: int, pending: int = 0
) -> int:
    """How many new pairs to label now, so the dataset grows in step with training and reaches the budget at the end.

    :param pending: pairs already asked for and still waiting for their label (:attr:`PreferenceSource.pending`)
    """
    progress = min(1.0, num_timesteps / max(total_timesteps, 1))
    wanted = max(1, int(label_budget * progress)) - len(dataset) - pending
    return max(0, min(wanted, MAX_NEW_PAIRS_PER_ROUND, dataset.remaining - pending))


def flat_pair_observations(pairs: TrajectoryPairs) -> dict[str, np.ndarray]:
    """Every step of both trajectories of every pair as one batch: ``(2, B, T, ...)`` -> ``(2 B T, ...)``."""
    return {key: value.reshape(-1, *value.shape[3:]) for key, value in pairs.observations.items()}


def save_preference_data(path: str | Path, trajectory_buffer: TrajectoryBuffer, dataset: PreferenceDataset) -> None:
    """The stored trajectories and labelled pairs of a checkpoint, as one npz file (read back without pickle).

    The file is written under a temporary name and renamed into place, so it is never found half-written.
    """
    arrays = {f"trajectories/{key}": value for key, value in trajectory_buffer.state_dict().items()}
    arrays.update({f"preferences/{key}": value for key, value in dataset.to_arrays().items()})
    save_npz(path, arrays)


def read_preference_data(
    path: str | Path, trajectory_buffer: TrajectoryBuffer, label_budget: int, pair_length: int | None = None
) -> tuple[dict[str, np.ndarray], PreferenceDataset]:
    """Read and check what :func:`save_preference_data` wrote, changing nothing.

    :param path: the npz file
    :param trajectory_buffer: the model's buffer, which the stored trajectories must fit
    :param label_budget: the model's ``n_preference_pairs``; stored pairs beyond it are dropped, with a warning
    :param pair_length: T of the model's pairs (default: whole trajectories, ``trajectory_buffer.max_length``)
    :return: the trajectory buffer's state (for ``trajectory_buffer.load_state_dict``) and the labelled pairs
    """
    fix = (
        "save_replay_buffer writes it beside the replay buffer: keep the two together, or load the files of another "
        "complete checkpoint."
    )
    arrays = read_npz(path, "preference file", fix)
    trajectories = _checked_trajectory_state(_with_prefix(arrays, "trajectories/"), trajectory_buffer, str(path))
    dataset = PreferenceDataset.from_arrays(
        _with_prefix(arrays, "preferences/"),
        label_budget,
        str(path),
        PairShapes.of(trajectory_buffer, pair_length),
        capacity_name="n_preference_pairs",
    )
    return trajectories, dataset


def load_preference_data(
    path: str | Path, trajectory_buffer: TrajectoryBuffer, label_budget: int, pair_length: int | None = None
) -> PreferenceDataset:
    """Restore what :func:`save_preference_data` wrote: fills ``trajectory_buffer`` and returns the labelled pairs.

    All or nothing: on any error ``trajectory_buffer`` is unchanged (arguments as in :func:`read_preference_data`).
    """
    trajectories, dataset = read_preference_data(path, trajectory_buffer, label_budget, pair_length)
    trajectory_buffer.load_state_dict(trajectories)
    return dataset


def _with_prefix(arrays: dict[str, np.ndarray], prefix: str) -> dict[str, np.ndarray]:
    return {key.removeprefix(prefix): value for key, value in arrays.items() if key.startswith(prefix)}


def _checked_trajectory_state(
    arrays: dict[str, np.ndarray], trajectory_buffer: TrajectoryBuffer, source: str
) -> dict[str, np.ndarray]:
    """The stored trajectories, if they fit ``trajectory_buffer`` exactly (same keys, shapes and capacity). A file saved
    before trajectories recorded who drove them has no ``goal_driven``: none was the goal-driven control's; one saved
    before they recorded their episodes' seeds has no ``episode_seeds``: none is known."""
    expected = trajectory_buffer.state_dict()
    if "goal_driven" not in arrays and "lengths" in arrays:
        arrays = {**arrays, "goal_driven": np.zeros(arrays["lengths"].shape, dtype=bool)}
    if "episode_seeds" not in arrays and "lengths" in arrays:
        arrays = {**arrays, "episode_seeds": np.full(arrays["lengths"].shape, -1, dtype=np.int64)}
    missing = sorted(set(expected) - set(arrays))
    unknown = sorted(set(arrays) - set(expected))
    if missing:
        raise ValueError(f"Malformed preference file {source}: missing {[f'trajectories/{key}' for key in missing]}")
    if unknown:
        raise ValueError(
            f"Malformed preference file {source}: {[f'trajectories/{key}' for key in unknown]} are not in the model's "
            "trajectory buffer: was the file saved by a model of another env?"
        )
    for key, wanted in expected.items():
        found = arrays[key]
        if key != "position" and found.shape[:1] != wanted.shape[:1]:
            raise ValueError(
                f"The preference file {source} holds {found.shape[0]} trajectories but the model keeps "
                f"{wanted.shape[0]}: build the model with trajectory_buffer_size={found.shape[0]} to load it"
            )
        if found.shape != wanted.shape:
            raise ValueError(
                f"Malformed preference file {source}: trajectories/{key} has shape {found.shape}, the model's "
                f"{wanted.shape}: was it saved by a model of another env or with another option_steps?"
            )
        _check_numbers(found, f"trajectories/{key}", source)
    lengths, (position, full) = arrays["lengths"], arrays["position"]
    if np.any(lengths < 0) or np.any(lengths > trajectory_buffer.max_length) or not 0 <= position < len(lengths):
        raise ValueError(f"Malformed preference file {source}: trajectory lengths or position out of range")
    if full not in (0, 1):
        raise ValueError(f"Malformed preference file {source}: trajectories/position must be [position, 0 or 1]")
    if not np.all(np.isin(arrays["goal_driven"], (0, 1))):
        raise ValueError(f"Malformed preference file {source}: trajectories/goal_driven must hold booleans (0 or 1)")
    if arrays["episode_seeds"].dtype.kind not in "iu" or np.any(arrays["episode_seeds"] < -1):
        raise ValueError(
            f"Malformed preference file {source}: trajectories/episode_seeds must hold integer seeds (or -1: unknown)"
        )
    return {key: arrays[key] for key in expected}


def _check_numbers(array: np.ndarray, key: str, source: str) -> None:
    if array.dtype.kind not in "biuf":
        raise ValueError(f"Malformed preference file {source}: {key} must hold numbers, not {array.dtype}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"Malformed preference file {source}: {key} holds NaN or infinite values")


def _allocate_like(pairs: TrajectoryPairs, capacity: int) -> TrajectoryPairs:
    def empty(array: np.ndarray) -> np.ndarray:
        return np.zeros((array.shape[0], capacity, *array.shape[2:]), dtype=array.dtype)

    return TrajectoryPairs(
        observations={key: empty(value) for key, value in pairs.observations.items()},
        actions=empty(pairs.actions),
        reached_actions=empty(pairs.reached_actions),
        next_achieved_goals=empty(pairs.next_achieved_goals),
        mask=empty(pairs.mask),
        labels=np.zeros(capacity, dtype=np.float32),
    )


def _write(store: np.ndarray, values: np.ndarray, start: int, count: int) -> None:
    if store.ndim == 1:
        store[start : start + count] = values[:count]
    else:
        store[:, start : start + count] = values[:, :count]


def pairs_from_arrays(arrays: dict[str, np.ndarray], source: str, shapes: PairShapes | None = None) -> TrajectoryPairs:
    """Pairs from named arrays (the schema of :meth:`PreferenceDataset.load`), every array checked: finite numbers,
    labels in {0, 0.5, 1}, a 0/1 mask, consistent shapes (given ``shapes``, the model's).

    :param arrays: the named arrays
    :param source: where they come from (a file), named in every message
    :param shapes: the shapes the pairs must have (``None``: consistent with each other)
    """
    observation_keys = [key.split("/", 1)[1] for key in arrays if key.startswith("observations/")]
    required_observations = GOAL_KEYS if shapes is None else tuple(shapes.observations)
    required = ["labels", "mask", "actions", "reached_actions", "next_achieved_goals"]
    missing = [key for key in required + [f"observations/{key}" for key in required_observations] if key not in arrays]
    if missing:
        raise ValueError(f"Malformed preference file {source}: missing {missing}")
    if shapes is not None and set(observation_keys) != set(shapes.observations):
        raise ValueError(
            f"Malformed preference file {source}: observation keys {sorted(observation_keys)}, the model's are "
            f"{sorted(shapes.observations)}: were the pairs made on another env?"
        )
    for key in required + [f"observations/{key}" for key in observation_keys]:
        _check_numbers(arrays[key], key, source)
    labels = arrays["labels"].astype(np.float32)
    n_pairs = labels.shape[0] if labels.ndim == 1 else -1
    if labels.ndim != 1 or not np.all(np.isin(labels, (0.0, 0.5, 1.0))):
        raise ValueError(f"Malformed preference file {source}: labels must be a vector of 0, 0.5 or 1")
    mask = arrays["mask"]
    if mask.ndim != 3 or mask.shape[:2] != (2, n_pairs):
        raise ValueError(f"Malformed preference file {source}: mask must have shape (2, {n_pairs}, T), got {mask.shape}")
    if not np.all(np.isin(mask, (0, 1))):
        raise ValueError(f"Malformed preference file {source}: mask must hold booleans (0 or 1)")
    horizon = mask.shape[2]
    if shapes is not None and horizon != shapes.length:
        raise ValueError(
            f"Malformed preference file {source}: its pairs have T={horizon} steps, the model's have {shapes.length}: "
            "were they made with another option_steps, episode length or segment_length?"
        )
    for key, step_shape in _step_shapes(arrays, shapes, observation_keys).items():
        if arrays[key].shape[:3] != (2, n_pairs, horizon):
            raise ValueError(
                f"Malformed preference file {source}: {key} must start with shape (2, {n_pairs}, {horizon}), "
                f"got {arrays[key].shape}"
            )
        # Goal envs here have 1-D spaces (validation.check_goal_observation_space): one size per step.
        if len(step_shape) != 1 or arrays[key].shape[3:] != step_shape:
            size = step_shape[0] if len(step_shape) == 1 else "size"
            raise ValueError(
                f"Malformed preference file {source}: {key} must have shape (2, {n_pairs}, {horizon}, {size}), got "
                f"{arrays[key].shape}" + ("" if shapes is None else ": were the pairs made on another env?")
            )
    return TrajectoryPairs(
        observations={key: arrays[f"observations/{key}"].astype(np.float32) for key in observation_keys},
        actions=arrays["actions"].astype(np.float32),
        reached_actions=arrays["reached_actions"].astype(np.float32),
        next_achieved_goals=arrays["next_achieved_goals"].astype(np.float32),
        mask=mask.astype(bool),
        labels=labels,
    )


def _step_shapes(
    arrays: dict[str, np.ndarray], shapes: PairShapes | None, observation_keys: list[str]
) -> dict[str, tuple[int, ...]]:
    """The shape one step of each array must have: the model's, or else one consistent with the file's own arrays."""
    if shapes is None:
        observation_shapes = {key: arrays[f"observations/{key}"].shape[3:] for key in observation_keys}
        action_shape = arrays["actions"].shape[3:]
    else:
        observation_shapes, action_shape = dict(shapes.observations), (shapes.action_dim,)
    return {
        **{f"observations/{key}": shape for key, shape in observation_shapes.items()},
        "actions": action_shape,
        "reached_actions": action_shape,
        "next_achieved_goals": observation_shapes["achieved_goal"],
    }
