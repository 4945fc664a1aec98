"""Preference sources beyond the primitive-in-the-loop labeller: noisy scripted labels and labels from people.

:class:`NoisyLabeler` flips the scripted answer with probability ``noise`` (a simulated, imperfect person).
:class:`ProgressTieBreaker` answers the scripted labeller's ties by which trajectory ended nearer the goal.
:class:`QueuedPreferenceSource` sends pairs to people through a :class:`~sb3_dipper.labelling.queue.LabelQueue`
directory and hands them to training when the answers arrive; with ``person_fraction < 1`` or ``to_person`` it labels
the other pairs with the script at once (mixed mode), and records who labelled each pair.

DIPPER, PIPER and DPO-FLAT take either as ``preference_source``, or a YAML-friendly description of one (a string or a
dict, see :func:`preference_source_from`), so the zoo's YAML files and ``-params`` can choose them.
"""

from __future__ import annotations

import copy
import math
import warnings
from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np
from stable_baselines3.common.vec_env import VecEnv

from sb3_dipper.common.preferences import (
    MAX_NEW_PAIRS_PER_ROUND,
    GoalReachedFn,
    PathDistanceFn,
    PreferenceSource,
    PrimitiveInTheLoopLabeler,
    TrajectoryPairs,
    labels_from_scores,
    path_distance_gains,
    progress_gain_labels,
    progress_labels,
)
from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.common.validation import as_bool, sparse_goal_reached_fn
from sb3_dipper.labelling.drawable import DRAWN_ENVS, why_page_cannot_draw
from sb3_dipper.labelling.queue import PERSON, SCRIPT, LabelQueue

PreferenceSourceSpec = PreferenceSource | str | dict[str, Any] | None

SPEC_HELP = (
    "a PreferenceSource, None (primitive-in-the-loop labels), 'primitive', 'progress' (ties broken by the distance to "
    "the goal at the end), 'progress:gain' (ties broken by how much nearer the goal each trajectory ended than it "
    "started), 'progress:path_gain' (the same along a maze's free cells; Fetch mazes only), 'noisy:P[:SEED]', "
    "'people:DIRECTORY', 'mixed:DIRECTORY:FRACTION', or a dict with kind ('progress', 'noisy', 'people' or 'mixed') "
    "and the source's keyword arguments"
)

# How fast a person labels on the labelling page: about ten seconds a pair (look at both pictures against the goal,
# press a key), so six pairs a minute.
PAIRS_A_PERSON_LABELS_A_MINUTE = 6
# A run that asks people for more pairs than this is warned about at setup: at the pace above it is about three hours
# of one person's labelling, more than a person gives a run in one sitting. Beyond it the queue grows faster than
# anyone answers (one file a pair), and the label budget is not met.
PEOPLE_PAIRS_WARNING_THRESHOLD = 1_000


class NoisyLabeler(PreferenceSource):
    """The scripted (primitive-in-the-loop) answer, flipped with probability ``noise``; ties answered at random.

    Every label is 0 or 1, as from a person who must pick one trajectory and errs at rate ``noise``.

    :param noise: the probability of flipping the scripted answer, in [0, 0.5]
    :param seed: seed of the flips and tie-breaks
    :param script: the scripted labeller (default: the algorithm's primitive-in-the-loop labeller)
    """

    def __init__(self, noise: float, seed: int | None = 0, script: PreferenceSource | None = None) -> None:
        if not isinstance(noise, (int, float)) or not 0.0 <= noise <= 0.5:
            raise ValueError(
                f"NoisyLabeler noise must be a probability in [0, 0.5], got {noise!r}: above 0.5 the labels mostly "
                "disagree with the script (swap the preference instead)"
            )
        self.noise = float(noise)
        self.seed = seed
        self.script = script
        self._rng = np.random.default_rng(seed)

    def label(self, pairs: TrajectoryPairs) -> np.ndarray:
        if self.script is None:
            raise ValueError("NoisyLabeler needs a script: pass script=..., or give it to an algorithm as preference_source")
        labels = np.asarray(self.script.label(pairs), dtype=np.float32).copy()
        ties = labels == 0.5
        labels[ties] = self._rng.integers(2, size=int(ties.sum()))
        flip = self._rng.random(labels.shape[0]) < self.noise
        labels[flip] = 1.0 - labels[flip]
        return labels


class ProgressTieBreaker(PreferenceSource):
    """The scripted (primitive-in-the-loop) answer, with its ties answered by progress: of two trajectories that reached
    the goal equally often, the one that ended nearer to it is preferred (``measure="end"``), or the one that came
    nearer to it than it started by more (``measure="gain"``), or by more along the free space between walls
    (``measure="path_gain"``, with ``path_distances``).

    Beyond the paper. Where the lower level seldom reaches the goal, nearly every primitive-in-the-loop label is a tie
    and carries nothing for the higher level to learn; the distance at the end still tells the pairs apart. The
    distance is measured in goal coordinates, so it is an oracle of the task's geometry, not of the lower level. On
    tasks whose starts and goals are drawn at random the two trajectories of a pair start apart, and the distance at
    the end prefers the one that began nearer its goal, whatever its subgoals did; the gain compares what each
    trajectory achieved (on a fixed task both start alike and the two measures agree). On a maze the straight
    distance prefers a gripper pressed against the wall nearest the goal; the path gain prefers the way round it.

    :param script: the scripted labeller (default: the algorithm's primitive-in-the-loop labeller)
    :param measure: ``"end"`` (:func:`~sb3_dipper.common.preferences.progress_labels`), ``"gain"``
        (:func:`~sb3_dipper.common.preferences.progress_gain_labels`) or ``"path_gain"``
        (:func:`~sb3_dipper.common.preferences.path_distance_gains`)
    :param path_distances: with ``"path_gain"``, how far points lie from their goals along the free space
        (:data:`~sb3_dipper.common.preferences.PathDistanceFn`; default, given to an algorithm: its env's
        ``maze.path_distances``)
    """

    MEASURES: ClassVar[dict[str, Callable[[TrajectoryPairs], np.ndarray]]] = {
        "end": progress_labels,
        "gain": progress_gain_labels,
    }
    #: every measure: those of :attr:`MEASURES` and ``"path_gain"``, which needs ``path_distances``
    NAMES: ClassVar[tuple[str, ...]] = (*MEASURES, "path_gain")

    def __init__(
        self, script: PreferenceSource | None = None, measure: str = "end", path_distances: PathDistanceFn | None = None
    ) -> None:
        if measure not in self.NAMES:
            raise ValueError(f"ProgressTieBreaker measure must be one of {sorted(self.NAMES)}, got {measure!r}")
        self.script = script
        self.measure = measure
        self.path_distances = path_distances

    def label(self, pairs: TrajectoryPairs) -> np.ndarray:
        if self.script is None:
            raise ValueError(
                "ProgressTieBreaker needs a script: pass script=..., or give it to an algorithm as preference_source"
            )
        labels = np.asarray(self.script.label(pairs), dtype=np.float32).copy()
        ties = labels == 0.5
        labels[ties] = self._progress_labels(pairs.select(np.flatnonzero(ties)))
        return labels

    def _progress_labels(self, pairs: TrajectoryPairs) -> np.ndarray:
        if self.measure in self.MEASURES:
            return self.MEASURES[self.measure](pairs)
        if self.path_distances is None:
            raise ValueError(
                "ProgressTieBreaker(measure='path_gain') needs path_distances: pass path_distances=..., or give it to "
                "an algorithm on a maze env, whose maze.path_distances it takes"
            )
        return labels_from_scores(path_distance_gains(pairs, self.path_distances))


def maze_path_distances(env: VecEnv | None) -> PathDistanceFn:
    """The free-space distance of ``env``'s maze (``env.unwrapped.maze.path_distances``, the Fetch mazes), for
    ``preference_source="progress:path_gain"``; a ``ValueError`` naming ``preference_source`` on an env without one."""
    maze = env.get_attr("maze")[0] if env is not None and env.has_attr("maze") else None
    path_distances = getattr(maze, "path_distances", None)
    if not callable(path_distances):
        env_id = queue_info(env, None)["env_id"]
        raise ValueError(
            "preference_source 'progress:path_gain' measures progress along a maze's free cells, and the env "
            f"{'' if env_id is None else repr(env_id) + ' '}has no maze geometry (maze.path_distances; the Fetch mazes "
            "have one): use 'progress' or 'progress:gain' on it"
        )
    return path_distances


class QueuedPreferenceSource(PreferenceSource):
    """Labels from people: pairs are queued in ``directory`` and reach training when someone labels them.

    :meth:`label` never waits: it answers NaN for the pairs it queues, and :meth:`collect` returns those labelled since
    (skipped pairs are dropped). Pairs meant for people once ``budget`` pairs were queued get the script's label, or
    none without a script. A source started on a directory with queued pairs takes over those still waiting; with
    ``reuse_labels`` it also hands training every label already given (a run restarted from scratch keeps people's
    work). A model whose dataset is restored from its saved file (``load_replay_buffer``, as when a checkpoint
    resumes) holds the pairs handed to training before that save already, as the file records
    (:attr:`~sb3_dipper.common.preferences.PreferenceDataset.handed_ids`): those are not handed again; every other
    label, given since the save or handed to training after it and lost with a killed run, is. An algorithm refuses the
    source on an env the labelling page cannot draw (:func:`check_page_can_draw`).

    :param directory: the label queue directory, shared with the page (``sb3-dipper-label --run DIRECTORY``)
    :param person_fraction: the share of new pairs sent to people; the script labels the others at once (mixed mode)
    :param to_person: ``to_person(pairs) -> (B,) bool``, which pairs go to people (replaces ``person_fraction``)
    :param budget: the most pairs ever queued for people in ``directory`` (``None``: only the algorithm's budget)
    :param script: the scripted labeller of the others (default: the algorithm's primitive-in-the-loop labeller)
    :param reuse_labels: hand training the labels already in ``directory`` when the source starts
    :param seed: seed of the draw of which pairs go to people
    """

    def __init__(
        self,
        directory: str,
        person_fraction: float = 1.0,
        to_person: Callable[[TrajectoryPairs], np.ndarray] | None = None,
        budget: int | None = None,
        script: PreferenceSource | None = None,
        reuse_labels: bool = True,
        seed: int | None = 0,
    ) -> None:
        if not isinstance(person_fraction, (int, float)) or not 0.0 <= person_fraction <= 1.0:
            raise ValueError(f"person_fraction must be a share in [0, 1], got {person_fraction!r}")
        if budget is not None and (not isinstance(budget, int) or budget < 0):
            raise ValueError(f"budget must be an integer >= 0 (pairs queued for people) or None, got {budget!r}")
        self.directory = str(directory)
        self.person_fraction = float(person_fraction)
        self.to_person = to_person
        self.budget = budget
        self.script = script
        self.reuse_labels = as_bool("reuse_labels", reuse_labels)
        self.seed = seed
        self.queue_info: dict[str, Any] = {}
        self._queue: LabelQueue | None = None
        self._pending: set[int] = set()
        self._handed: set[int] = set()
        # The labels not to hand over: those in the directory at take-over when not reuse_labels.
        self._not_reused: set[int] = set()
        # The pairs collect handed to training, in order.
        self._delivered: list[int] = []
        self._next_id = 0
        self._rng = np.random.default_rng(seed)

    @property
    def queue(self) -> LabelQueue:
        """The directory's files; the first use takes over what an earlier run left there."""
        if self._queue is None:
            queue = LabelQueue(self.directory)
            queue.directory.mkdir(parents=True, exist_ok=True)
            if self.queue_info:
                queue.write_info(self.queue_info)
            self._pending = set(queue.waiting_ids())
            self._not_reused = set() if self.reuse_labels else set(queue.answers().pair_ids.tolist())
            self._handed = set(self._not_reused)
            self._next_id = queue.next_free_id()
            self._queue = queue
        return self._queue

    @property
    def handed_ids(self) -> np.ndarray:
        return np.array(self._delivered, dtype=np.int64)

    def dataset_restored(self, handed_ids: np.ndarray | None = None) -> None:
        queue = self.queue  # after the first use's take-over, which this may be
        if handed_ids is None:
            # A file saved before datasets recorded their pairs: the directory's record of hand-overs stands in (it
            # also lists pairs handed after that save, which are then not handed again).
            handed = queue.read_handed()
            handed_ids = handed["pair_id"][handed["labeller"] == PERSON]
        self._delivered = [int(pair_id) for pair_id in handed_ids]
        self._handed = self._not_reused | set(self._delivered)

    @property
    def pending(self) -> int:
        answered = set(self.queue.answers().pair_ids.tolist())  # first: the first use takes over waiting pairs
        return len(self._pending - answered)

    def label(self, pairs: TrajectoryPairs) -> np.ndarray:
        queue = self.queue
        n_pairs = len(pairs)
        if self.to_person is not None:
            for_person = np.asarray(self.to_person(pairs), dtype=bool).reshape(n_pairs)
        else:
            for_person = self._rng.random(n_pairs) < self.person_fraction
        if self.budget is not None:
            room = max(0, self.budget - len(queue.queued_ids()))
            for_person &= np.cumsum(for_person) <= room
        labels = np.full(n_pairs, np.nan, dtype=np.float32)
        pair_ids = np.arange(self._next_id, self._next_id + n_pairs)
        self._next_id += n_pairs
        for index in np.flatnonzero(for_person):
            queue.write_pair(int(pair_ids[index]), pairs, int(index))
            self._pending.add(int(pair_ids[index]))
        scripted = np.flatnonzero(~for_person)
        if scripted.size and self.script is not None:
            labels[scripted] = self.script.label(pairs.select(scripted))
            queue.append_handed(pair_ids[scripted], labels[scripted], np.full(scripted.size, SCRIPT))
        return labels

    def collect(self) -> TrajectoryPairs | None:
        queue = self.queue
        answers = queue.answers().as_dict()
        self._pending -= set(answers)
        labelled = [pair_id for pair_id, label in answers.items() if not math.isnan(label)]
        arrived = sorted(pair_id for pair_id in labelled if pair_id not in self._handed)
        if not arrived:
            return None
        batch = concatenate_pairs([queue.read_pair(pair_id, answers[pair_id]) for pair_id in arrived])
        self._handed.update(arrived)
        self._delivered.extend(arrived)
        queue.append_handed(np.array(arrived), batch.labels, np.full(len(arrived), PERSON))
        return batch

    def __getstate__(self) -> dict[str, Any]:
        # The file cache is rebuilt from the directory on first use.
        return {**self.__dict__, "_queue": None}


def concatenate_pairs(batches: list[TrajectoryPairs]) -> TrajectoryPairs:
    """One batch of all pairs of ``batches`` (same keys and trajectory length)."""
    return TrajectoryPairs(
        observations={key: np.concatenate([b.observations[key] for b in batches], axis=1) for key in batches[0].observations},
        actions=np.concatenate([b.actions for b in batches], axis=1),
        reached_actions=np.concatenate([b.reached_actions for b in batches], axis=1),
        next_achieved_goals=np.concatenate([b.next_achieved_goals for b in batches], axis=1),
        mask=np.concatenate([b.mask for b in batches], axis=1),
        labels=np.concatenate([b.labels for b in batches]).astype(np.float32),
    )


def queue_info(env: VecEnv | None, subgoal_space: SubgoalSpace | None) -> dict[str, Any]:
    """What the page needs to draw the pairs of a model: its env id and kwargs, and its subgoal space (if any)."""
    info: dict[str, Any] = {"env_id": None, "env_kwargs": {}, "subgoal_space": None}
    if env is not None:
        spec = env.get_attr("spec", indices=[0])[0]
        if spec is not None:
            info["env_id"] = spec.id
            info["env_kwargs"] = {key: value for key, value in spec.kwargs.items() if _is_json(value)}
    if subgoal_space is not None:
        info["subgoal_space"] = {
            "low": subgoal_space.low.tolist(),
            "high": subgoal_space.high.tolist(),
            "threshold": float(subgoal_space.threshold),
            "indices": None if subgoal_space.indices is None else list(subgoal_space.indices),
        }
    return info


def _is_json(value: Any) -> bool:
    if isinstance(value, (list, tuple)):
        return all(_is_json(item) for item in value)
    if isinstance(value, dict):
        return all(isinstance(key, str) and _is_json(item) for key, item in value.items())
    return value is None or isinstance(value, (bool, int, float, str))


def pairs_for_people(source: QueuedPreferenceSource, label_budget: int) -> int:
    """The most pairs ``source`` queues for people over a run whose label budget is ``label_budget``.

    The algorithm asks for its whole budget over the run (:func:`~sb3_dipper.common.preferences.pairs_due`); people get
    ``person_fraction`` of it (all of it when ``to_person`` chooses), at most the source's own ``budget``.
    """
    share = 1.0 if source.to_person is not None else source.person_fraction
    pairs = math.ceil(label_budget * share)
    return pairs if source.budget is None else min(pairs, source.budget)


def warn_if_beyond_people(source: QueuedPreferenceSource, label_budget: int) -> None:
    """Warn when a run would ask people for more pairs than :data:`PEOPLE_PAIRS_WARNING_THRESHOLD`.

    :param source: the algorithm's source of labels from people
    :param label_budget: the algorithm's ``n_preference_pairs``
    """
    pairs = pairs_for_people(source, label_budget)
    if pairs <= PEOPLE_PAIRS_WARNING_THRESHOLD:
        return
    pace = PAIRS_A_PERSON_LABELS_A_MINUTE
    hours = pairs / pace / 60
    an_hour = 60 * pace
    warnings.warn(
        f"n_preference_pairs={label_budget:,} asks people for up to {pairs:,} pairs over the run (label queue "
        f"{source.directory}), about {hours:,.0f} hours of labelling at {pace} pairs a minute. Training queues them as "
        f"it goes, up to {MAX_NEW_PAIRS_PER_ROUND} per training round, one file each, whether or not anyone labels "
        "them. Size the label budget to the labelling people will do: n_preference_pairs = pairs a minute x minutes "
        f"of labelling (n_preference_pairs={an_hour} for one person and one hour), divided by the people's share in "
        "mixed mode; or cap the pairs sent to people and let the script label the rest: "
        f"preference_source={{'kind': 'people', 'directory': {source.directory!r}, 'budget': {an_hour}}}."
    )


def check_page_can_draw(source: QueuedPreferenceSource) -> None:
    """Refuse a source whose pairs the labelling page cannot draw: people would be asked about pairs they cannot see.

    :param source: the source, its ``queue_info`` set from the model's env
    :raises ValueError: naming ``preference_source``, the env, why, and the fix
    """
    reason = why_page_cannot_draw(source.queue_info)
    if reason is None:
        return
    env_id = source.queue_info["env_id"]
    raise ValueError(
        f"preference_source sends pairs to people (label queue {source.directory!r}), but the labelling page cannot "
        f"draw the pairs of {'this env' if env_id is None else f'env {env_id!r}'} ({reason}): it draws {DRAWN_ENVS}. "
        "Register the env id with gymnasium.register (for an env the page draws), or label with the script: "
        "preference_source=None (the default labels), 'progress' or 'noisy:P'."
    )


def preference_source_from(
    spec: PreferenceSourceSpec,
    script: PreferenceSource,
    env: VecEnv | None = None,
    subgoal_space: SubgoalSpace | None = None,
    seed: int | None = None,
    label_budget: int | None = None,
) -> PreferenceSource:
    """The preference source an algorithm's ``preference_source`` describes, using ``script`` where it needs one.

    A source that was given without a script gets ``script`` in a copy, so the algorithm's own labeller (which may
    hold the model) never enters the configured ``preference_source`` the model saves.

    :param spec: :data:`SPEC_HELP`
    :param script: the algorithm's primitive-in-the-loop labeller
    :param env: the model's env, whose id and kwargs a label queue records for the page; an env the page cannot draw
        is refused (:func:`check_page_can_draw`). Without it the queue records no env, and the page draws no pair.
    :param subgoal_space: the model's subgoal space (``None``: pairs of primitive actions), recorded for the page
    :param seed: the model's seed, for sources described without one
    :param label_budget: the algorithm's ``n_preference_pairs``: a source that would ask people for far more pairs
        than they can label is warned about (:func:`warn_if_beyond_people`)
    """
    if spec is None or spec == "primitive":
        return script
    if isinstance(spec, str):
        spec = _parse_spec(spec)
    if isinstance(spec, dict):
        options = dict(spec)
        kind = options.pop("kind", None)
        classes: dict[str, type[PreferenceSource]] = {
            "progress": ProgressTieBreaker,
            "noisy": NoisyLabeler,
            "people": QueuedPreferenceSource,
        }
        if kind == "mixed":
            kind = "people"
            options.setdefault("person_fraction", 0.5)
        if kind not in classes:
            raise ValueError(f"Unknown preference_source kind {kind!r}: preference_source is {SPEC_HELP}")
        if kind != "progress":
            options.setdefault("seed", seed)
        try:
            spec = classes[kind](**options)
        except TypeError as error:
            raise ValueError(f"Bad preference_source {spec!r} ({error}): preference_source is {SPEC_HELP}") from error
    if not isinstance(spec, PreferenceSource):
        raise ValueError(f"Bad preference_source {spec!r}: preference_source is {SPEC_HELP}")
    # A copy: the algorithm's script (which may hold the model) must not enter the saved preference_source.
    if isinstance(spec, ProgressTieBreaker) and spec.script is None:
        spec = copy.copy(spec)
        spec.script = script
        if spec.measure not in ProgressTieBreaker.MEASURES and spec.path_distances is None:
            spec.path_distances = maze_path_distances(env)
    if isinstance(spec, QueuedPreferenceSource) or (isinstance(spec, NoisyLabeler) and spec.script is None):
        spec = copy.copy(spec)
        spec.script = spec.script or script
        spec._rng = np.random.default_rng(spec.seed)
        if isinstance(spec, QueuedPreferenceSource):
            spec.queue_info = queue_info(env, subgoal_space)
            if env is not None:
                check_page_can_draw(spec)
            spec._pending, spec._handed, spec._not_reused, spec._delivered, spec._queue = set(), set(), set(), [], None
            if label_budget is not None:
                warn_if_beyond_people(spec, label_budget)
    return spec


def preference_labeler(
    spec: PreferenceSourceSpec,
    env: VecEnv,
    subgoal_space: SubgoalSpace | None,
    seed: int | None,
    value_score: Callable[[TrajectoryPairs], np.ndarray] | None = None,
    goal_reached: GoalReachedFn | None = None,
    label_budget: int | None = None,
) -> PreferenceSource:
    """The labeller of an algorithm (DIPPER, PIPER, DPO-FLAT): its ``preference_source`` on ``env``, with the
    primitive-in-the-loop labeller of the env's sparse reward as the script (:func:`preference_source_from`).

    :param spec: the algorithm's ``preference_source``, :data:`SPEC_HELP`
    :param env: the model's env
    :param subgoal_space: the model's subgoal space (``None``: pairs of primitive actions), recorded for the page
    :param seed: the model's seed, for sources described without one
    :param value_score: a term added to the primitive-in-the-loop score (the lower value), ``(2, B)`` per pair
    :param goal_reached: the env's sparse goal test, if the algorithm has it already (default: read from the env)
    :param label_budget: the algorithm's ``n_preference_pairs`` (:func:`warn_if_beyond_people`)
    """
    script = PrimitiveInTheLoopLabeler(goal_reached or sparse_goal_reached_fn(env), value_score)
    return preference_source_from(spec, script, env, subgoal_space, seed, label_budget)


def label_queue_directory(spec: PreferenceSourceSpec) -> str | None:
    """The label queue directory a ``preference_source`` sends pairs to people through (``None``: no people).

    :param spec: :data:`SPEC_HELP`
    """
    if isinstance(spec, str) and spec != "primitive":
        spec = _parse_spec(spec)
    if isinstance(spec, dict) and spec.get("kind") in ("people", "mixed") and "directory" in spec:
        return str(spec["directory"])
    if isinstance(spec, QueuedPreferenceSource):
        return spec.directory
    return None


def _parse_spec(text: str) -> dict[str, Any]:
    kind, _, rest = text.partition(":")
    try:
        if kind == "progress" and (not rest or rest in ProgressTieBreaker.NAMES):
            return {"kind": "progress", **({"measure": rest} if rest else {})}
        if kind == "noisy":
            noise, _, seed = rest.partition(":")
            return {"kind": "noisy", "noise": float(noise), **({"seed": int(seed)} if seed else {})}
        if kind == "people" and rest:
            return {"kind": "people", "directory": rest}
        if kind == "mixed" and rest:
            directory, _, fraction = rest.rpartition(":")
            if not directory:
                return {"kind": "mixed", "directory": rest}
            return {"kind": "mixed", "directory": directory, "person_fraction": float(fraction)}
    except ValueError as error:
        raise ValueError(f"Bad preference_source {text!r} ({error}): preference_source is {SPEC_HELP}") from error
    raise ValueError(f"Bad preference_source {text!r}: preference_source is {SPEC_HELP}")
