"""Runs longer than a sitting, trained in parts: ``sb3-dipper-zoo train --pause-after-minutes M`` and ``--resume``.

A paused run leaves a resume checkpoint in its run folder (:class:`PauseCheckpointCallback`: the model, its replay
buffers and normalisation statistics in ``<run>/resume/``). ``--resume RUN_FOLDER`` continues that run in its folder to
its whole budget: it refuses hyperparameters other than the run's own (:func:`check_resumed_hyperparameters`) and
another budget (:func:`resumed_n_timesteps`; without ``-n`` it trains to the run's own), keeps the run's records of
how it started (``config.yml``, ``args.yml``), sets the logs of the part trained so far aside (:func:`set_aside_part`),
lets the evaluations go on on the run's grid (:func:`continue_evaluations`), trains what is left of the budget
(:func:`learn_resumed`) and removes the checkpoint once the final model is written (:func:`remove_resume_checkpoint`).
:mod:`sb3_dipper.zoo.exp_manager` calls these from rl-zoo3's experiment manager.
"""

from __future__ import annotations

import io
import json
import shutil
import time
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback, EvalCallback
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

from sb3_dipper.common.deprecation import in_new_form
from sb3_dipper.common.files import read_npz, write_bytes_atomically
from sb3_dipper.zoo.algorithms import ZOO_ALGORITHMS
from sb3_dipper.zoo.callbacks import PROGRESS_FILE, STEPS_KEY, read_progress
from sb3_dipper.zoo.run_config import ARGS_FILE, CONFIG_FILE, as_recorded, recorded_hyperparameters

# A paused run's checkpoint: <run folder>/resume/model.zip and the files beside it.
RESUME_FOLDER = "resume"
RESUME_MODEL = "model.zip"
# The evaluations EvalCallback records in the run folder, rewritten whole at every evaluation.
EVALUATIONS_FILE = "evaluations.npz"


class PauseCheckpointCallback(BaseCallback):
    """After ``minutes`` of training, stop training and save everything training needs to continue.

    The checkpoint ``<run>/resume/`` holds the model (``model.zip``), its replay buffers (``replay_buffer.pkl`` and, for
    the hierarchical algorithms, the higher level's files beside it) and the ``VecNormalize`` statistics when the env
    is normalised (``<env>/vecnormalize.pkl``, where rl-zoo3 looks for them). It is written to ``resume.tmp/`` and
    renamed into place, so a run killed while pausing keeps its previous checkpoint whole.

    The checkpoint is saved when training ends, not in ``on_step``: the step that triggers the pause is counted before
    it is stored, so a checkpoint saved there would count a step its buffers lack. By the end of training our
    algorithms have stored it (the option ends there); for SB3's off-policy algorithms, which skip storing the step that
    stopped training, it is stored here, as SB3 would have stored it had training gone on.

    :param minutes: training time before the pause, measured from the start of ``learn``
    :param run_folder: the run folder
    :param env_name: the env id, the name of rl-zoo3's folder for the normalisation statistics
    """

    def __init__(self, minutes: float, run_folder: Path, env_name: str) -> None:
        super().__init__()
        self.seconds = 60.0 * minutes
        self.run_folder = run_folder
        self.env_name = env_name
        self.paused = False
        self.saved = False

    def _init_callback(self) -> None:
        if not hasattr(self.model, "save_replay_buffer"):
            raise ValueError(
                f"--pause-after-minutes: {type(self.model).__name__} has no replay buffer to save; pausing and "
                "resuming is for off-policy algorithms (ours, SAC, TQC, ...)."
            )
        self.start = time.monotonic()

    def _on_step(self) -> bool:
        if time.monotonic() - self.start < self.seconds:
            return True
        self.paused = True
        return False

    def _on_training_end(self) -> None:
        # rl-zoo3 ends training a second time for its first callback (to close the progress bar): save once.
        if self.paused and not self.saved:
            self._store_interrupted_step()
            self.save_checkpoint()
            self.saved = True

    def _store_interrupted_step(self) -> None:
        """Store the step SB3's ``collect_rollouts`` counted but returned before storing (``on_step`` said stop)."""
        model = self.model
        if isinstance(model, OffPolicyAlgorithm) and "buffer_actions" in self.locals:
            step = self.locals
            model._update_info_buffer(step["infos"], step["dones"])
            model._store_transition(
                model.replay_buffer,  # type: ignore[arg-type]
                step["buffer_actions"],
                step["new_obs"],
                step["rewards"],
                step["dones"],
                step["infos"],
            )

    def save_checkpoint(self) -> None:
        staging = self.run_folder / f"{RESUME_FOLDER}.tmp"
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir()
        self.model.save(staging / RESUME_MODEL)
        self.model.save_replay_buffer(staging / "replay_buffer.pkl")  # type: ignore[attr-defined]
        normalize = self.model.get_vec_normalize_env()
        if normalize is not None:
            (staging / self.env_name).mkdir()
            normalize.save(str(staging / self.env_name / "vecnormalize.pkl"))
        replace_folder(staging, self.run_folder / RESUME_FOLDER)


def replace_folder(staging: Path, target: Path) -> None:
    """Put ``staging`` at ``target``; an old ``target`` is moved aside first and removed last."""
    old = target.with_name(target.name + ".old")
    shutil.rmtree(old, ignore_errors=True)
    if target.exists():
        target.rename(old)
    staging.rename(target)
    shutil.rmtree(old, ignore_errors=True)


def saved_steps(model_zip: Path) -> tuple[int, int]:
    """``num_timesteps`` and ``_total_timesteps`` of a saved model, from the JSON part of its zip (no pickle)."""
    with zipfile.ZipFile(model_zip) as archive:
        data = json.loads(archive.read("data"))
    return int(data["num_timesteps"]), int(data.get("_total_timesteps", 0))


def checkpoint_steps(run_folder: Path) -> int:
    """The primitive steps the run's resume checkpoint has trained."""
    return saved_steps(run_folder / RESUME_FOLDER / RESUME_MODEL)[0]


def differing_hyperparameters(started: Mapping[str, Any], given: Mapping[str, Any]) -> list[tuple[str, Any, Any]]:
    """``(name, started with, given)`` for every hyperparameter that differs (``None`` for one not set), by name.

    A ``use_sde`` entry in a recorded ``*policy_kwargs`` dict that the given one lacks is no difference: SB3's SAC
    writes its ``use_sde`` into the ``policy_kwargs`` it is handed, and rl-zoo3 records that dict after the model is
    built (sb3-dipper's hierarchical algorithms handed theirs to SAC too before they copied it). Nor is a ``gamma`` in
    a recorded ``normalize`` dict that equals the given ``gamma``: rl-zoo3 writes the algorithm's discount into the
    ``normalize`` dict it is handed (``VecNormalize`` discounts returns with it) before it records the dict.
    """
    differing = []
    for name in sorted(set(started) | set(given)):
        recorded, wanted = started.get(name), given.get(name)
        if isinstance(recorded, dict) and isinstance(wanted, dict):
            if name.endswith("policy_kwargs") and "use_sde" in recorded and "use_sde" not in wanted:
                recorded = {key: value for key, value in recorded.items() if key != "use_sde"}
            own_gamma = "gamma" in recorded and recorded["gamma"] == given.get("gamma")
            if name == "normalize" and own_gamma and "gamma" not in wanted:
                recorded = {key: value for key, value in recorded.items() if key != "gamma"}
        if recorded != wanted:
            differing.append((name, started.get(name), given.get(name)))
    return differing


def run_env_folder(run_folder: Path, env_name: str) -> Path:
    """``<run>/<env>/``, where rl-zoo3 records the run's configuration; an error naming ``--env`` if the run has none.

    :raises ValueError: the run folder has no folder for ``env_name`` (it trained another env, listed)
    """
    folder = run_folder / env_name
    if folder.is_dir() or not run_folder.is_dir():
        return folder
    trained = sorted(path.name for path in run_folder.iterdir() if (path / CONFIG_FILE).is_file())
    raise ValueError(
        f"--resume {run_folder}: the run has no folder {env_name}/, so it did not train --env {env_name}"
        + (f"; it trained {', '.join(trained)}: resume it with that --env." if trained else ".")
    )


def run_record(path: Path, what: str) -> dict[str, Any]:
    """What rl-zoo3 recorded in ``path`` (``<run>/<env>/config.yml`` or ``args.yml``) when the run started.

    :param what: what the file records, for the message if it is missing (``"hyperparameters"``, ``"flags"``)
    :raises FileNotFoundError: there is no ``path``; the message names it and the fix
    """
    try:
        return recorded_hyperparameters(path)
    except FileNotFoundError:
        raise FileNotFoundError(
            f"{path} is missing: rl-zoo3 writes the {what} a run starts with there, and --resume checks the ones given "
            "against them. Restore it from a copy of the run folder, or start a new run (without --resume)."
        ) from None


def check_resume_checkpoint(run_folder: Path, env_name: str, normalized: bool) -> None:
    """Refuse a resume checkpoint that lacks a file :class:`PauseCheckpointCallback` writes: rl-zoo3 loads the replay
    buffer and the normalisation statistics only where they exist, so without them the run would go on silently from
    an empty buffer or new statistics.

    :param normalized: whether the run normalises its env (``normalize`` in its hyperparameters)
    """
    checkpoint = run_folder / RESUME_FOLDER
    needed = [checkpoint / "replay_buffer.pkl"] + ([checkpoint / env_name / "vecnormalize.pkl"] if normalized else [])
    missing = [str(path) for path in needed if not path.is_file()]
    if missing:
        raise FileNotFoundError(
            f"--resume {run_folder}: the resume checkpoint lacks {', '.join(missing)}, which pausing writes beside "
            f"{RESUME_MODEL}; without it the run would go on from an empty replay buffer or new normalisation "
            "statistics. Restore the checkpoint whole from a copy of the run folder, or start a new run."
        )


def check_resumed_evaluations(run_folder: Path, env_name: str, given: Mapping[str, Any]) -> None:
    """Refuse to resume a run with other evaluation flags than its own (recorded by rl-zoo3 in ``<env>/args.yml``): a
    row of another ``--eval-episodes`` cannot join the run's evaluation record, and another ``--eval-freq`` would move
    the resumed evaluations off the run's grid.

    :param given: the flags of this command, by their names in ``args.yml`` (``eval_freq``, ``eval_episodes``)
    """
    started = run_record(run_folder / env_name / ARGS_FILE, "flags")
    differing = [
        f"--{name.replace('_', '-')} {value} (the run's: {started.get(name)})"
        for name, value in given.items()
        if name in started and started[name] != value
    ]
    if differing:
        raise ValueError(
            f"--resume {run_folder}: {', '.join(differing)}. A resumed run evaluates as it started, so that its "
            f"evaluations stay one record ({EVALUATIONS_FILE}); resume it with the run's flags, or start a new run."
        )


def resumed_n_timesteps(run_folder: Path, env_name: str, given: int) -> int:
    """The ``-n`` a resumed run trains to: the budget the run was started with.

    rl-zoo3 records ``-n`` in ``<env>/args.yml`` as ``n_timesteps`` (-1 for a run started without ``-n``, which trains
    to the ``n_timesteps`` of its hyperparameters, recorded in ``config.yml``). A resume without ``-n`` trains to the
    run's own budget, whichever it was; another ``-n`` is refused: a smaller one would end the run at once and remove
    its resume checkpoint, a larger one would make it another experiment than the one it started as.

    :param given: the ``-n`` of this command, as rl-zoo3 reads it (<= 0 when left out)
    :return: the ``-n`` to train to, as rl-zoo3 reads it (<= 0: the ``n_timesteps`` of the hyperparameters)
    :raises ValueError: ``given`` is another budget than the run's; the message names both and the fix
    """
    recorded_flags = run_record(run_folder / env_name / ARGS_FILE, "flags")
    if "n_timesteps" not in recorded_flags:
        return given
    recorded = int(recorded_flags["n_timesteps"])
    if given <= 0 or given == recorded:
        return recorded
    if recorded > 0:
        budget, started = recorded, f"it was started with -n {recorded} ({run_folder / env_name / ARGS_FILE})"
    else:
        config = run_folder / env_name / CONFIG_FILE
        budget = int(float(run_record(config, "hyperparameters")["n_timesteps"]))
        if given == budget:
            return given
        started = f"it was started without -n, so it trains to the n_timesteps of its hyperparameters ({config})"
    raise ValueError(
        f"--resume {run_folder}: -n {given}, but the run's budget is {budget:,} primitive steps: {started}. A resumed "
        f"run trains to the budget it was started with: resume it with -n {budget} or without -n. To train another "
        "budget, start a new run (leave out --resume)."
    )


def check_resumed_hyperparameters(run_folder: Path, env_name: str, given: Mapping[str, Any]) -> None:
    """Refuse to resume a run with hyperparameters (YAML entry, ``-params``, Optuna trial) other than its own.

    rl-zoo3 hands the hyperparameters given to ``load``, which sets them on the model: a resumed run would continue
    with new values and save them into its next checkpoint, a different experiment under the same run folder.

    :param run_folder: the run folder given to ``--resume``
    :param env_name: the env's folder name in the run folder, where rl-zoo3 writes ``config.yml``
    :param given: the hyperparameters of this command, as rl-zoo3 records them
    """
    config = run_folder / env_name / CONFIG_FILE
    started = run_record(config, "hyperparameters")
    # A run started with the lower level's bc_coef: 0.02 resumes with demo_kwargs: {bc_coef: 0.02}, the same setting.
    started, wanted = (
        in_new_form(hyperparameters, ZOO_ALGORITHMS.values()) for hyperparameters in (started, as_recorded(given))
    )
    differing = differing_hyperparameters(started, wanted)
    if not differing:
        return
    lines = "\n".join(
        f"  {name}: started with {'(not set)' if started is None else repr(started)}, given "
        f"{'(not set)' if wanted is None else repr(wanted)}"
        for name, started, wanted in differing
    )
    raise ValueError(
        f"--resume {run_folder}: the hyperparameters given differ from those the run was started with ({config}):\n"
        f"{lines}\nA resumed run continues the same experiment. Resume it with the command that started it (the same "
        "-params and hyperparameter file), or train these hyperparameters in a new run: leave out --resume."
    )


def recorded_evaluations(run_folder: Path) -> dict[str, np.ndarray] | None:
    """The evaluations recorded in the run folder's ``evaluations.npz`` (``None`` if there are none yet), checked.

    ``EvalCallback`` rewrites the whole file at every evaluation, in place: a run killed meanwhile leaves it cut short.
    """
    path = run_folder / EVALUATIONS_FILE
    if not path.exists():
        return None
    fix = (
        "It holds the evaluations of the run so far (a run killed while an evaluation was written leaves it cut "
        "short): restore it from a copy of the run folder, or delete it to resume with the evaluations from the "
        "checkpoint on only."
    )
    return read_npz(path, "evaluation record", fix, required=("timesteps", "results", "ep_lengths"))


def set_aside_part(run_folder: Path) -> None:
    """Move the monitor files and ``progress.csv`` of the part trained so far into ``<run>/part_<k>/``.

    The resumed part writes its own (both are created afresh, ``progress.csv`` exclusively); ``zoo_scripts/plot.py``
    reads the ``progress.csv`` and the monitor files of every part in order. A part killed after its last checkpoint
    logged steps and episodes the resumed run trains again: those ``progress.csv`` rows (by step) and monitor episodes
    (those that ended after the checkpoint was written) are dropped, so every step and episode is logged once.

    :raises ValueError: ``progress.csv`` is damaged (:func:`~sb3_dipper.zoo.callbacks.read_progress`); nothing is moved
    """
    logs = [*run_folder.glob("*.monitor.csv"), *run_folder.glob(PROGRESS_FILE)]
    if not logs:
        return
    progress = run_folder / PROGRESS_FILE
    # Read before anything moves, so that a damaged log is refused where the message says it is, the run folder as it was.
    rows = read_progress(progress) if progress.exists() else None
    part = run_folder / f"part_{1 + len(list(run_folder.glob('part_*')))}"
    part.mkdir()
    for path in logs:
        path.rename(part / path.name)
    if rows is not None and STEPS_KEY in rows:
        kept = rows[rows[STEPS_KEY] <= checkpoint_steps(run_folder)]
        write_bytes_atomically(part / PROGRESS_FILE, kept.to_csv(index=False).encode())
    checkpoint_time = (run_folder / RESUME_FOLDER / RESUME_MODEL).stat().st_mtime
    for monitor in part.glob("*.monitor.csv"):
        drop_episodes_after(monitor, checkpoint_time)


def drop_episodes_after(monitor: Path, wall_time: float) -> None:
    """Keep the episodes of an SB3 monitor file that ended by ``wall_time`` (seconds since the epoch).

    SB3's ``Monitor`` writes a ``#{"t_start": ...}`` line, then one row per finished episode with ``t``, its end in
    seconds after ``t_start``.
    """
    header, _, table = monitor.read_text().partition("\n")
    if not header.startswith("#") or not table.strip():
        return
    episodes = pd.read_csv(io.StringIO(table))
    kept = episodes[json.loads(header[1:])["t_start"] + episodes["t"] <= wall_time]
    if len(kept) < len(episodes):
        write_bytes_atomically(monitor, f"{header}\n{kept.to_csv(index=False)}".encode())


def continue_evaluations(callbacks: list[BaseCallback], num_timesteps: int, n_envs: int, run_folder: Path) -> None:
    """Let a resumed run's callbacks go on where the paused run's stopped.

    Step-counting callbacks (evaluation, checkpoints) count calls, one per vectorised step: they are set to the steps
    already trained, so evaluations stay every ``--eval-freq`` steps from the start of the run. ``EvalCallback`` gets
    the evaluations already recorded in ``evaluations.npz`` (it rewrites the whole file at every evaluation) and the
    best mean reward among them (so ``best_model.zip`` is replaced only by a better one).
    """
    for callback in callbacks:
        callback.n_calls = num_timesteps // n_envs
        if not isinstance(callback, EvalCallback):
            continue
        data = recorded_evaluations(run_folder)
        if data is None:
            continue
        # Evaluations after the checkpoint (a part killed before its next pause) are made again.
        kept = data["timesteps"] <= num_timesteps
        callback.evaluations_timesteps = [int(step) for step in data["timesteps"][kept]]
        callback.evaluations_results = [list(results) for results in data["results"][kept]]
        callback.evaluations_length = [list(lengths) for lengths in data["ep_lengths"][kept]]
        if "successes" in data:
            callback.evaluations_successes = [list(successes) for successes in data["successes"][kept]]
        if callback.evaluations_results:
            callback.best_mean_reward = max(float(np.mean(results)) for results in callback.evaluations_results)


def learn_resumed(model: BaseAlgorithm, n_timesteps: int, callbacks: list[BaseCallback], log_interval: int) -> bool:
    """rl-zoo3's ``ExperimentManager.learn`` for a resumed run: train what is left of the budget.

    rl-zoo3 restarts a loaded model's step count (``reset_num_timesteps=True``) and trains ``-n`` more steps; a resumed
    run continues its count. The rest (log interval, closing the progress bar and the env) is rl-zoo3's.

    :return: whether the whole budget is trained (and the run did not pause again): then, once rl-zoo3 has written the
        final model, nothing is left to resume (:func:`remove_resume_checkpoint`)
    """
    kwargs: dict[str, Any] = {"reset_num_timesteps": False, "callback": callbacks}
    if log_interval > -1:
        kwargs["log_interval"] = log_interval
    elif log_interval < -1:
        kwargs["log_interval"] = None
    try:
        model.learn(max(n_timesteps - model.num_timesteps, 0), **kwargs)
    except KeyboardInterrupt:
        pass
    finally:
        if callbacks:
            callbacks[0].on_training_end()
        assert model.env is not None
        model.env.close()
    paused_again = any(isinstance(callback, PauseCheckpointCallback) and callback.paused for callback in callbacks)
    return model.num_timesteps >= n_timesteps and not paused_again


def remove_resume_checkpoint(run_folder: Path) -> None:
    """Remove the resume checkpoint of a run whose final model is written: it is moved aside, then deleted, so a run
    killed meanwhile has either the whole checkpoint or none (and its final model either way)."""
    checkpoint = run_folder / RESUME_FOLDER
    if checkpoint.exists():
        retired = run_folder / f"{RESUME_FOLDER}.done"
        shutil.rmtree(retired, ignore_errors=True)
        checkpoint.rename(retired)
        shutil.rmtree(retired)
