"""rl-zoo3's experiment manager as ``sb3-dipper-zoo train`` runs it: each run claims its own folder, and a run pauses,
resumes (:mod:`sb3_dipper.zoo.resume`) and serves the labelling page while it trains as :class:`RunControl` says.

rl-zoo3 patches gymnasium's ``TimeLimit`` when imported, so :func:`install_experiment_manager` imports it only when
called.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_dipper.common.deprecation import completed_groups
from sb3_dipper.labelling.training_page import start_label_page
from sb3_dipper.zoo.callbacks import AtomicEvalCallback, CSVProgressCallback
from sb3_dipper.zoo.resume import (
    RESUME_FOLDER,
    RESUME_MODEL,
    PauseCheckpointCallback,
    check_resume_checkpoint,
    check_resumed_evaluations,
    check_resumed_hyperparameters,
    continue_evaluations,
    learn_resumed,
    recorded_evaluations,
    remove_resume_checkpoint,
    resumed_n_timesteps,
    run_env_folder,
    set_aside_part,
)
from sb3_dipper.zoo.run_config import yaml_entry

if TYPE_CHECKING:
    import optuna
    from rl_zoo3.exp_manager import ExperimentManager as _ExperimentManager
else:  # rl-zoo3 is imported only when the experiment manager is installed (it patches gymnasium's TimeLimit)
    _ExperimentManager = object


def claim_run_folder(log_path: str, env_name: str, run_id: int, suffix: str = "") -> str:
    """Create the run folder ``<log_path>/<env_name>_<run_id><suffix>``, or the first free id after ``run_id``.

    The folder is created exclusively (``mkdir`` fails if it exists), so runs started together with the same log
    folder each get their own, where rl-zoo3 would hand them all the next free id and mix their files.

    :param log_path: the algorithm's log folder (created if missing)
    :param env_name: the env id the run folders are named after
    :param run_id: the first id to try
    :param suffix: what follows the id (rl-zoo3's ``--uuid``)
    :return: the path of the created folder
    """
    os.makedirs(log_path, exist_ok=True)
    while True:
        save_path = os.path.join(log_path, f"{env_name}_{run_id}{suffix}")
        try:
            os.mkdir(save_path)
        except FileExistsError:
            run_id += 1
        else:
            return save_path


@dataclass
class RunControl:
    """Our own flags of ``sb3-dipper-zoo train``, read before rl-zoo3 parses the rest.

    :param pause_after_minutes: ``--pause-after-minutes M``: after M minutes of training, save a resume checkpoint in
        the run folder and stop (rl-zoo3 then saves the model as usual)
    :param resume: ``--resume RUN_FOLDER``: continue that run from its resume checkpoint, in the same folder, to the
        budget it was started with
    :param label_page: ``--label-page [HOST:]PORT``: serve the labelling page of the model's label queue (its
        ``preference_source`` is ``people:DIR`` or ``mixed:DIR:FRACTION``) while it trains, as ``(host, port)``
    """

    pause_after_minutes: float | None = None
    resume: Path | None = None
    label_page: tuple[str, int] | None = None

    def check_resumable(
        self, env_name: str, hyperparameters: Mapping[str, Any], evaluation_flags: Mapping[str, Any], n_timesteps: int
    ) -> int:
        """With ``--resume``, refuse before anything changes a run that cannot continue as it was: another env than
        the run's, other hyperparameters, evaluation flags or budget than its own (:func:`check_resumed_hyperparameters`,
        :func:`check_resumed_evaluations`, :func:`resumed_n_timesteps`), a checkpoint without its buffers or statistics
        (:func:`check_resume_checkpoint`), or a damaged evaluation record.

        :param env_name: the env's folder name in the run folder
        :param hyperparameters: the hyperparameters given, as rl-zoo3 read them
        :param evaluation_flags: ``eval_freq`` and ``eval_episodes`` given, as rl-zoo3 records them in ``args.yml``
        :param n_timesteps: ``-n`` as given (<= 0 when left out)
        :return: the ``-n`` to train to: the one given, or with ``--resume`` the run's own
        """
        if self.resume is None:
            return n_timesteps
        run_env_folder(self.resume, env_name)
        check_resumed_hyperparameters(self.resume, env_name, hyperparameters)
        check_resumed_evaluations(self.resume, env_name, evaluation_flags)
        n_timesteps = resumed_n_timesteps(self.resume, env_name, n_timesteps)
        # rl-zoo3 normalises for any `normalize` entry but False (a dict or a string of one included).
        normalized = hyperparameters.get("normalize", False) not in (None, False)
        check_resume_checkpoint(self.resume, env_name, normalized)
        recorded_evaluations(self.resume)
        return n_timesteps


class TrialsKeepTheEntrysGroups(_ExperimentManager):
    """rl-zoo3's experiment manager whose Optuna trials change only the keys they sample of a dict whose keys are
    settings of their own (:meth:`~sb3_dipper.common.loading.CheckedLoading.setting_groups`, DIPPER's
    ``switch_kwargs``; :func:`~sb3_dipper.common.deprecation.completed_groups`).

    rl-zoo3 sets a trial's hyperparameters over the entry's, a dict over the entry's whole dict: a trial sampling
    ``switch_kwargs["nll_coef"]`` would turn the entry's other switches off, where it changed ``nll_coef`` alone when
    the switches were parameters. Here a sampled trial (``-optimize``) and a stored one (``--trial-id``) keep them.
    """

    def hyperparameters_optimization(self) -> None:
        from rl_zoo3.hyperparams_opt import HYPERPARAMS_SAMPLER

        sampler = HYPERPARAMS_SAMPLER[self.algo]

        def sampler_keeping_the_entrys_groups(
            trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict
        ) -> dict[str, Any]:
            sampled = sampler(trial, n_actions, n_envs, additional_args)
            return completed_groups(self._setting_groups(), sampled, self._hyperparams)

        HYPERPARAMS_SAMPLER[self.algo] = sampler_keeping_the_entrys_groups
        try:
            super().hyperparameters_optimization()
        finally:
            HYPERPARAMS_SAMPLER[self.algo] = sampler

    def load_trial(self, storage: str, study_name: str, trial_id: int | None = None, convert: bool = True) -> dict[str, Any]:
        params = super().load_trial(storage, study_name, trial_id, convert)
        # rl-zoo3 has read the entry by now (read_hyperparameters), but does not keep it: read it again, from a YAML file.
        if not convert or not self.config.endswith((".yml", ".yaml")):
            return params
        return completed_groups(self._setting_groups(), params, yaml_entry(self.config, self.env_name.gym_id))

    def _setting_groups(self) -> set[str]:
        """The algorithm's dict parameters given key by key (:meth:`~sb3_dipper.common.loading.CheckedLoading.setting_groups`;
        none for SB3's own algorithms)."""
        from rl_zoo3.utils import ALGOS

        algorithm = ALGOS[self.algo]
        return algorithm.setting_groups() if hasattr(algorithm, "setting_groups") else set()


class RunRecordsKeptWhole(_ExperimentManager):
    """rl-zoo3's experiment manager that never leaves a run's records cut short or rewritten: its evaluation callback
    writes ``evaluations.npz`` to a temporary file and renames it into place (:class:`AtomicEvalCallback`), the
    :class:`CSVProgressCallback` of the hyperparameters writes ``progress.csv`` in the run folder (with any
    ``--vec-env``), and a resumed run (``resuming``) keeps the records of how it started (``<env>/config.yml``,
    ``args.yml``, ``command.txt``), which rl-zoo3 would rewrite in place.
    """

    resuming = False

    def create_callbacks(self) -> None:
        import rl_zoo3.exp_manager

        # rl-zoo3 makes its evaluation callback from the EvalCallback of its module.
        eval_callback_class = rl_zoo3.exp_manager.EvalCallback
        rl_zoo3.exp_manager.EvalCallback = AtomicEvalCallback  # type: ignore[misc]
        try:
            super().create_callbacks()
        finally:
            rl_zoo3.exp_manager.EvalCallback = eval_callback_class  # type: ignore[misc]
        for callback in self.callbacks:
            if isinstance(callback, CSVProgressCallback) and callback.folder is None:
                # Where the run's monitor files are, which the callback cannot ask of --vec-env subproc's workers.
                callback.folder = Path(self.save_path)

    def _save_config(self, saved_hyperparams: dict[str, Any]) -> None:
        if not self.resuming:
            super()._save_config(saved_hyperparams)
            return
        # The next --resume checks the flags and hyperparameters given against these records; rewritten by a resume
        # without -n, args.yml would lose the run's -n and the next resume would train to the YAML budget.
        print(f"Log path: {self.save_path} (resumed: the records of how the run started, in {self.params_path}, are kept)")


def install_experiment_manager(control: RunControl | None = None) -> None:
    """Make rl-zoo3's train create each run's folder with :func:`claim_run_folder` and obey ``control``.

    :param control: ``--pause-after-minutes`` and ``--resume`` (idempotent: the last call's control counts)
    """
    import rl_zoo3.train
    from rl_zoo3.exp_manager import ExperimentManager
    from rl_zoo3.utils import get_latest_run_id

    run_control = control or RunControl()

    class OwnRunFolderExperimentManager(TrialsKeepTheEntrysGroups, RunRecordsKeptWhole, ExperimentManager):
        """rl-zoo3's experiment manager whose run folder is claimed exclusively when it is created, and which pauses
        and resumes runs (:class:`RunControl`)."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            # rl-zoo3's train passes its --uuid suffix by keyword.
            self.run_folder_suffix = kwargs.get("uuid_str", "")
            if run_control.resume is not None:
                # rl-zoo3's own continuation: it loads the model, the replay buffer beside it and, from
                # <dir>/<env>/vecnormalize.pkl, the normalisation statistics.
                self.trained_agent = str(run_control.resume / RESUME_FOLDER / RESUME_MODEL)
                self.continue_training = True
                self.resuming = True

        def read_hyperparameters(self) -> tuple[dict[str, Any], dict[str, Any]]:
            hyperparams, saved_hyperparams = super().read_hyperparameters()
            # Before anything in the run folder changes (create_log_folder sets the last part's logs aside).
            # self.n_timesteps is still -n as given (args.yml's n_timesteps): rl-zoo3 puts the YAML budget in its place later.
            evaluation_flags = {"eval_freq": self.eval_freq, "eval_episodes": self.n_eval_episodes}
            self.n_timesteps = run_control.check_resumable(
                str(self.env_name), saved_hyperparams, evaluation_flags, self.n_timesteps
            )
            return hyperparams, saved_hyperparams

        def create_log_folder(self) -> None:
            if run_control.resume is not None:
                self.save_path = str(run_control.resume)
                self.params_path = f"{self.save_path}/{self.env_name}"
                set_aside_part(run_control.resume)
            else:
                run_id = get_latest_run_id(self.log_path, self.env_name) + 1
                self.save_path = claim_run_folder(self.log_path, self.env_name, run_id, self.run_folder_suffix)
                self.params_path = f"{self.save_path}/{self.env_name}"
            super().create_log_folder()

        def create_callbacks(self) -> None:
            super().create_callbacks()
            if run_control.pause_after_minutes is not None:
                pause = PauseCheckpointCallback(run_control.pause_after_minutes, Path(self.save_path), self.env_name)
                self.callbacks.append(pause)

        def setup_experiment(self) -> Any:
            experiment = super().setup_experiment()
            if experiment is not None and run_control.resume is not None:
                model = experiment[0]
                continue_evaluations(self.callbacks, model.num_timesteps, model.n_envs, run_control.resume)
            return experiment

        def learn(self, model: BaseAlgorithm) -> None:
            page = None if run_control.label_page is None else start_label_page(model, *run_control.label_page)
            try:
                if run_control.resume is None:
                    super().learn(model)
                else:
                    self.resumed_to_the_end = learn_resumed(model, self.n_timesteps, self.callbacks, self.log_interval)
            finally:
                if page is not None:
                    page.shutdown()

        def save_trained_model(self, model: BaseAlgorithm) -> None:
            super().save_trained_model(model)
            # Only now: a run killed before its final model is written keeps its checkpoint, and --resume still works.
            if run_control.resume is not None and getattr(self, "resumed_to_the_end", False):
                remove_resume_checkpoint(run_control.resume)

    rl_zoo3.train.ExperimentManager = OwnRunFolderExperimentManager  # type: ignore[misc]
