"""Callbacks of zoo runs: the one our hyperparameter files name under ``callback`` (rl-zoo3 imports it by its dotted
name), and the evaluation callback :mod:`sb3_dipper.zoo.exp_manager` gives every ``sb3-dipper-zoo train`` run."""

from __future__ import annotations

import os
from pathlib import Path

from stable_baselines3.common.callbacks import BaseCallback, EvalCallback
from stable_baselines3.common.logger import CSVOutputFormat

from sb3_dipper.common.files import npz_path


class CSVProgressCallback(BaseCallback):
    """Also write the logger's records to ``progress.csv`` beside the run's monitor files.

    rl-zoo3 logs to stdout (and TensorBoard); ``zoo_scripts/plot.py`` reads ``progress.csv`` for the hierarchical
    metrics (``rollout/subgoal_distance``, ``rollout/low_value``). Our YAML files name this class under ``callback``.
    The file is created exclusively: a run never appends its rows to another run's ``progress.csv``.
    """

    def _init_callback(self) -> None:
        writer = self.training_env.get_attr("results_writer", indices=[0])[0]
        if writer is None:  # a Monitor without a file: nowhere to put progress.csv
            return
        path = Path(writer.file_handler.name).parent / "progress.csv"
        try:
            path.open("x").close()
        except FileExistsError:
            raise FileExistsError(
                f"{path} already exists: another run logs to the same folder. Give each run its own monitor folder "
                "(sb3-dipper-zoo train does: it creates each run folder exclusively)."
            ) from None
        self.model.logger.output_formats.append(CSVOutputFormat(str(path)))

    def _on_step(self) -> bool:
        return True


class AtomicEvalCallback(EvalCallback):
    """SB3's ``EvalCallback`` whose evaluation record (``evaluations.npz``) is written to a temporary file beside it and
    renamed into place.

    SB3 rewrites the whole record in place at every evaluation: a run killed meanwhile would leave it cut short, and
    every evaluation so far with it. Here SB3's own code writes the record, so its keys and format stay SB3's and
    SB3's and rl-zoo3's tools read it as before; only where it is written changes. A kill leaves the previous record
    whole (and at most a ``.evaluations.<pid>.tmp.npz`` file).
    """

    def _on_step(self) -> bool:
        if self.log_path is None:
            return super()._on_step()
        record = self.log_path
        folder, name = os.path.split(record)
        temporary = os.path.join(folder, f".{name}.{os.getpid()}.tmp")
        evaluations = len(self.evaluations_timesteps)
        self.log_path = temporary
        try:
            continue_training = super()._on_step()
        except BaseException:
            npz_path(temporary).unlink(missing_ok=True)
            raise
        finally:
            self.log_path = record
        if len(self.evaluations_timesteps) > evaluations:
            with open(npz_path(temporary), "rb") as written:
                # Rename only what is on disk, as sb3_dipper.common.files.write_atomically does.
                os.fsync(written.fileno())
            os.replace(npz_path(temporary), npz_path(record))
        return continue_training
