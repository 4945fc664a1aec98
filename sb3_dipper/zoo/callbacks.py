"""Callbacks of zoo runs: the one our hyperparameter files name under ``callback`` (rl-zoo3 imports it by its dotted
name), with the writer and the checked reader of its ``progress.csv``, and the evaluation callback
:mod:`sb3_dipper.zoo.exp_manager` gives every ``sb3-dipper-zoo train`` run."""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path
from typing import Any
from weakref import WeakKeyDictionary

import pandas as pd
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback, EvalCallback
from stable_baselines3.common.logger import (
    Figure,
    FormatUnsupportedError,
    HParam,
    Image,
    KVWriter,
    Video,
    filter_excluded_keys,
)
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnvWrapper

from sb3_dipper.common.files import PathLike, npz_path, write_bytes_atomically

PROGRESS_FILE = "progress.csv"
STEPS_KEY = "time/total_timesteps"  # SB3's step count in progress.csv


def csv_cell(value: Any) -> str:
    """``value`` as SB3's ``CSVOutputFormat`` writes it in a cell: a string quoted (its quotes doubled), ``None`` (a key
    the record lacks) empty, anything else ``str(value)``.

    :raises FormatUnsupportedError: a video, figure, image or hyperparameter record, which SB3's CSV writer refuses too
    """
    for unsupported in (Video, Figure, Image, HParam):
        if isinstance(value, unsupported):
            raise FormatUnsupportedError(["csv"], unsupported.__name__.lower())
    if isinstance(value, str):
        return '"' + value.replace('"', '""') + '"'
    return "" if value is None else str(value)


class AtomicCSVOutputFormat(KVWriter):
    """SB3's ``CSVOutputFormat`` (its columns and cells) whose file is never left half-rewritten.

    SB3's writer rewrites the whole file in place whenever a record brings a new key (``train/...`` after
    ``learning_starts``, ``eval/...`` at the first evaluation): a run killed meanwhile leaves rows cut and spliced into
    others, which pandas reads without complaint. Here a record with the known keys is appended as one row, flushed; a
    record with new keys has the whole file written anew (the header, every earlier row with empty cells for the new
    columns, the record's row) to a temporary file renamed into place (:func:`~sb3_dipper.common.files.write_atomically`),
    so a kill leaves the previous file or the new one. New columns follow the known ones in the record's order (SB3
    adds them in a set's order, which varies between processes); readers find them by name.

    :param path: the CSV file; its content is replaced at the first record
    """

    def __init__(self, path: PathLike) -> None:
        self.path = Path(path)
        self.keys: list[str] = []

    def write(self, key_values: dict[str, Any], key_excluded: dict[str, tuple[str, ...]], step: int = 0) -> None:
        key_values = filter_excluded_keys(key_values, key_excluded, "csv")
        new_keys = [key for key in key_values if key not in self.keys]
        row = ",".join(csv_cell(key_values.get(key)) for key in [*self.keys, *new_keys]) + "\n"
        if not new_keys:
            # Opened for each row: the rename below replaces the file, which would leave a kept handle on the old one.
            with open(self.path, "a", encoding="utf-8", newline="") as file:
                file.write(row)
            return
        # Before the first record the file holds none of this writer's rows.
        earlier_rows = self.path.read_text(encoding="utf-8").split("\n")[1:-1] if self.keys else []
        padding = "," * len(new_keys)
        header = ",".join([*self.keys, *new_keys]) + "\n"
        content = header + "".join(f"{earlier}{padding}\n" for earlier in earlier_rows) + row
        write_bytes_atomically(self.path, content.encode())
        self.keys.extend(new_keys)

    def close(self) -> None:
        """Nothing to close: the file is opened for each row."""


def read_progress(path: PathLike) -> pd.DataFrame:
    """The rows of a run's ``progress.csv`` (an empty table for an empty file), refused if the file is damaged.

    SB3's own CSV writer (the zoo's before :class:`AtomicCSVOutputFormat`) rewrote the whole file in place at every new
    key: a run killed meanwhile left a file whose rows past the cut lack the new columns, with a spliced row before
    them and rows lost. pandas reads such a file without complaint. Here it is refused: a row whose number of fields
    differs from the header's, or whose step count (``time/total_timesteps``) is lower than the row's before it (an
    evaluation and a training record may log the same step).

    :raises ValueError: the file is damaged; the message names it, the line and what to do
    """
    path = Path(path)
    text = path.read_text(encoding="utf-8")
    if not text:
        return pd.DataFrame()

    def damaged(line: int, problem: str) -> ValueError:
        return ValueError(
            f"{path}: line {line} {problem}: the file is damaged (a run killed while SB3's CSV logger rewrote it leaves "
            f"such rows). To keep its earlier rows, delete line {line} and the lines after it (and line {line - 1} if "
            "its values look wrong); or delete the file, the run's log of its training metrics."
        )

    reader = csv.reader(io.StringIO(text))
    header = next(reader)
    steps_column = header.index(STEPS_KEY) if STEPS_KEY in header else None
    last_steps = -math.inf
    for row in reader:
        if len(row) != len(header):
            raise damaged(reader.line_num, f"has {len(row)} fields, the header {len(header)}")
        if steps_column is None or not row[steps_column]:
            continue
        try:
            steps = float(row[steps_column])
        except ValueError:
            raise damaged(reader.line_num, f"logs {STEPS_KEY} {row[steps_column]!r}, not a number") from None
        if steps < last_steps:
            problem = f"logs {STEPS_KEY} {row[steps_column]} after {last_steps:g} (a run's step count only grows)"
            raise damaged(reader.line_num, problem)
        last_steps = steps
    return pd.read_csv(io.StringIO(text))


# The progress.csv writer of each model given one, so that a later learn(..., reset_num_timesteps=False) of the same
# model (training in chunks) goes on with its file. Kept beside the model, not on it: SB3 would save it with the model.
_PROGRESS_WRITERS: WeakKeyDictionary[BaseAlgorithm, AtomicCSVOutputFormat] = WeakKeyDictionary()


class CSVProgressCallback(BaseCallback):
    """Also write the logger's records to ``progress.csv`` in the run's folder (:class:`AtomicCSVOutputFormat`).

    rl-zoo3 logs to stdout (and TensorBoard); ``zoo_scripts/plot.py`` reads ``progress.csv`` for the hierarchical
    metrics (``rollout/subgoal_distance``, ``rollout/low_value``). Our YAML files name this class under ``callback``.
    The file is created exclusively: a run never appends its rows to another run's ``progress.csv``. A later
    ``learn(..., reset_num_timesteps=False)`` of the same model, which continues its step count, appends to the file
    that model created.

    :param folder: where to write ``progress.csv``; by default beside the first env's monitor file, which only a
        ``DummyVecEnv`` can tell (a ``SubprocVecEnv``'s ``Monitor`` cannot be sent from its worker).
        ``sb3-dipper-zoo train`` passes the run folder unless the YAML entry gives one.
    :param verbose: verbosity level
    """

    def __init__(self, folder: PathLike | None = None, verbose: int = 0) -> None:
        super().__init__(verbose)
        self.folder = None if folder is None else Path(folder)

    def _init_callback(self) -> None:
        folder = self.folder if self.folder is not None else self._monitor_folder()
        if folder is None:  # a Monitor without a file: nowhere to put progress.csv
            return
        path = folder / PROGRESS_FILE
        writer = _PROGRESS_WRITERS.get(self.model)
        # A learn that restarts the step count (reset_num_timesteps=True) would log steps from 0 again into its file.
        if writer is None or writer.path != path or self.model.num_timesteps == 0:
            claim_progress_file(path, restarting=writer is not None and writer.path == path)
            writer = _PROGRESS_WRITERS[self.model] = AtomicCSVOutputFormat(path)
        # A logger the model keeps across learn calls (set_logger) has the writer already; SB3's own is made anew.
        if writer not in self.model.logger.output_formats:
            self.model.logger.output_formats.append(writer)

    def _monitor_folder(self) -> Path | None:
        """The folder of the first env's monitor file (None for a ``Monitor`` without a file), asked of the envs here.

        :raises ValueError: the envs are not in this process (not a ``DummyVecEnv``)
        """
        vec_env = self.training_env
        while isinstance(vec_env, VecEnvWrapper):
            vec_env = vec_env.venv
        if not isinstance(vec_env, DummyVecEnv):
            raise ValueError(
                f"CSVProgressCallback cannot find the run's monitor folder: the envs of a {type(vec_env).__name__} may "
                "live in other processes, from which their Monitor's open file cannot be sent. Pass the folder: "
                "CSVProgressCallback(folder=...) (sb3-dipper-zoo train passes the run folder)."
            )
        results_writer = vec_env.get_attr("results_writer", indices=[0])[0]
        return None if results_writer is None else Path(results_writer.file_handler.name).parent

    def _on_step(self) -> bool:
        return True


def claim_progress_file(path: Path, restarting: bool) -> None:
    """Create ``path`` exclusively (empty), so that no other run logs to it.

    :param restarting: whether the model logged to ``path`` in an earlier learn and this one restarts its step count
        (the message then says so)
    :raises FileExistsError: ``path`` exists; the message names it and the fix
    """
    try:
        path.open("x").close()
    except FileExistsError:
        if restarting:
            raise FileExistsError(
                f"{path} already exists: this model logged to it in an earlier learn, and this learn restarts the step "
                "count (reset_num_timesteps=True), so the log's steps would go back to 0. Pass "
                "reset_num_timesteps=False to continue the log, or give this training its own monitor folder."
            ) from None
        raise FileExistsError(
            f"{path} already exists: another run logs to the same folder. Give each run its own monitor folder "
            "(sb3-dipper-zoo train does: it creates each run folder exclusively)."
        ) from None


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
