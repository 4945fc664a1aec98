"""The preference pipeline of an algorithm that learns from labelled pairs (DIPPER, PIPER, DPO-FLAT).

:class:`PreferencePipeline` holds what such an algorithm's preferences are made of: the store of finished trajectories
(or episodes), the labelled dataset, the labeller and the pair sampler. Once per training round it labels the pairs
due (:meth:`PreferencePipeline.label_new_pairs`: the dataset grows in step with training up to the label budget),
and it saves and restores itself beside the replay buffer as one npz file (read without pickle), together with which
of people's labels the dataset holds. The algorithm decides only what its pairs are (a :class:`PairSampler`), how the
labeller scores them and what it learns from the dataset.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_dipper.common.preferences import (
    PairSampler,
    PreferenceDataset,
    PreferenceSource,
    TrajectoryPairs,
    add_new_labels,
    pairs_due,
    read_preference_data,
    save_preference_data,
)
from sb3_dipper.common.trajectories import TrajectoryBuffer


class PreferencePipeline:
    """Trajectories, labelled pairs, the labeller and pair sampling of one model, with its labelling schedule.

    :param trajectory_buffer: the finished trajectories (or episodes) the pairs are drawn from
    :param label_budget: the most pairs labelled over the whole run (the algorithm's ``n_preference_pairs``)
    :param sampler: draws the pairs to label
    :param labeler: labels them (``None`` for a model without an env, which labels nothing until it gets one)
    """

    def __init__(
        self,
        trajectory_buffer: TrajectoryBuffer,
        label_budget: int,
        sampler: PairSampler,
        labeler: PreferenceSource | None = None,
    ) -> None:
        self.trajectory_buffer = trajectory_buffer
        self.label_budget = label_budget
        self.dataset = PreferenceDataset(label_budget)
        self.sampler = sampler
        self.labeler = labeler

    def label_new_pairs(self, num_timesteps: int, total_timesteps: int, rng: np.random.Generator) -> TrajectoryPairs | None:
        """Label new pairs so that the dataset grows in step with training and reaches the label budget at its end.

        Labels that arrived since the last round (from people) join the dataset first; pairs still waiting for a label
        count as asked for. Then the pairs due are drawn, labelled and added.

        :param num_timesteps: the steps trained so far
        :param total_timesteps: the steps of the whole run
        :param rng: draws the pairs
        :return: the pairs drawn now, labelled (NaN: queued for a person); ``None`` when none were due or the buffer
            holds too few trajectories
        """
        assert self.labeler is not None, "a model labels pairs only once it has an env"
        add_new_labels(self.dataset, self.labeler, None)
        n_new = pairs_due(self.dataset, self.label_budget, num_timesteps, total_timesteps, self.labeler.pending)
        if n_new == 0 or len(self.trajectory_buffer) < self.sampler.min_trajectories:
            return None
        pairs = self.sampler.sample(self.trajectory_buffer, n_new, rng)
        pairs.labels = self.labeler.label(pairs)
        add_new_labels(self.dataset, self.labeler, pairs)
        return pairs

    def save(self, path: str | Path) -> None:
        """The trajectories and labelled pairs as one npz file (:func:`~sb3_dipper.common.preferences.save_preference_data`),
        written under a temporary name and renamed into place."""
        save_preference_data(path, self.trajectory_buffer, self.dataset)

    def read(self, path: str | Path) -> Callable[[], None]:
        """Read and check what :meth:`save` wrote, changing nothing; return the step that installs it.

        The step only assigns what was read, so it cannot fail half-way; it also tells the labeller which of its
        late labels (people's) the restored dataset holds.
        """
        trajectories, dataset = read_preference_data(path, self.trajectory_buffer, self.label_budget, self.sampler.pair_length)

        def install() -> None:
            self.trajectory_buffer.load_state_dict(trajectories)
            self.dataset = dataset
            if self.labeler is not None:
                self.labeler.dataset_restored(dataset.handed_ids)

        return install

    def load(self, path: str | Path) -> None:
        """Restore what :meth:`save` wrote, all or nothing: on an error (naming the file) nothing changes."""
        self.read(path)()


class PreferenceLearner(BaseAlgorithm):
    """Base of the algorithms that learn from labelled pairs through a :class:`PreferencePipeline`.

    The pipeline, ``preference_pipeline``, is built with the model's networks (``_setup_model``), its labeller from the
    algorithm's ``preference_source`` (:func:`~sb3_dipper.labelling.preference_labeler`), and it is not part
    of the saved model: ``save_replay_buffer`` saves it. Its trajectory buffer and dataset are also
    ``trajectory_buffer`` and ``preferences``.
    """

    preference_pipeline: PreferencePipeline

    @property
    def trajectory_buffer(self) -> TrajectoryBuffer:
        """The finished trajectories (DPO-FLAT: episodes) that preference pairs are drawn from."""
        return self.preference_pipeline.trajectory_buffer

    @trajectory_buffer.setter
    def trajectory_buffer(self, buffer: TrajectoryBuffer) -> None:
        self.preference_pipeline.trajectory_buffer = buffer

    @property
    def preferences(self) -> PreferenceDataset:
        """The labelled pairs, D."""
        return self.preference_pipeline.dataset

    @preferences.setter
    def preferences(self, dataset: PreferenceDataset) -> None:
        self.preference_pipeline.dataset = dataset

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "preference_pipeline"]
