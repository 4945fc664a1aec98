"""RL-Zoo integration: our algorithms, their hyperparameter files and Optuna samplers, registered into rl-zoo3.

rl-zoo3 has no plugin mechanism; its documented recipe for external algorithms is to add them to ``rl_zoo3.ALGOS``
(and, for ``-optimize``, to its sampler and converter tables) before calling its entry points. ``sb3-dipper-zoo``
does that, then runs rl-zoo3's own CLI with its own flags:

    sb3-dipper-zoo train --algo dipper --env PointMazeFourRooms-v0 --seed 0
    sb3-dipper-zoo enjoy --algo dipper --env PointMazeFourRooms-v0 -f logs/ --no-render -n 2000
    sb3-dipper-zoo train --algo dipper --env PointMazeFourRooms-v0 -optimize --storage logs/dipper.log --study-name s1

For the algorithms this package has hyperparameters for, ``train`` reads ``hyperparams/<algo>.yml`` unless
``--conf-file`` is given (rl-zoo3 takes its ``default`` entry for an env without an entry of its own). ``--env`` also
takes gymnasium's ``module:EnvId`` form. Each ``train`` run creates its run folder exclusively, so runs started
together with the same ``-f`` never share one.

Long runs can be trained in pieces: ``--pause-after-minutes M`` saves a resume checkpoint in the run folder after M
minutes of training and stops; ``--resume RUN_FOLDER`` (with the same other flags) continues that run in its folder to
its whole budget: same step count, evaluations on the same grid appended to the same ``evaluations.npz``, the replay
buffers as they were. The resumed part reseeds its random generators, so it is not the same run as one without a pause::

    sb3-dipper-zoo train --algo dipper --env FetchPushFixed-v0 -f logs --pause-after-minutes 80
    sb3-dipper-zoo train --algo dipper --env FetchPushFixed-v0 -f logs --resume logs/dipper/FetchPushFixed-v0_1

``--label-page [HOST:]PORT`` serves the labelling page (:mod:`sb3_dipper.labelling.app`) of the run's label queue from
the training process while it trains; the model's ``preference_source`` must send pairs to people::

    sb3-dipper-zoo train --algo dipper --env PointMazeFourRooms-v0 -params "preference_source:'people:logs/labels'" \
        --label-page 5000

That page stops when training ends; ``sb3-dipper-label --run logs/labels`` serves the queue on its own, for as long as
the person needs.

rl-zoo3 patches gymnasium's ``TimeLimit`` when imported, so it is
imported only here, and only when a command runs.
"""

from __future__ import annotations

import argparse
import importlib
import io
import json
import os
import runpy
import shutil
import sys
import time
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import optuna
import pandas as pd
import yaml
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback, EvalCallback
from stable_baselines3.common.logger import CSVOutputFormat
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

from sb3_dipper.common.deprecation import in_new_form
from sb3_dipper.common.files import read_npz, write_bytes_atomically
from sb3_dipper.dac import DAC
from sb3_dipper.dipper import DIPPER
from sb3_dipper.dpo_flat import DPOFlat
from sb3_dipper.hac import HAC
from sb3_dipper.hier import HIER
from sb3_dipper.labelling.sources import label_queue_directory
from sb3_dipper.piper import PIPER
from sb3_dipper.raps import RAPS
from sb3_dipper.saga import SAGA

# Zoo names: the same class can appear under several names so that comparison plots show each as its own line.
ZOO_ALGORITHMS: dict[str, type[BaseAlgorithm]] = {
    "dipper": DIPPER,
    "dipper_paper": DIPPER,
    "dipper_nov": DIPPER,
    "hier": HIER,
    "piper": PIPER,
    "saga": SAGA,
    "hac": HAC,
    "raps": RAPS,
    "dac": DAC,
    "dpo_flat": DPOFlat,
}

STEPS_KEY = "time/total_timesteps"  # SB3's step count in progress.csv
# A paused run's checkpoint: <run folder>/resume/model.zip and the files beside it.
RESUME_FOLDER = "resume"
RESUME_MODEL = "model.zip"
# What rl-zoo3 records in <run folder>/<env>/ when a run starts: its hyperparameters (and its flags in args.yml).
CONFIG_FILE = "config.yml"
# The evaluations EvalCallback records in the run folder, rewritten whole at every evaluation.
EVALUATIONS_FILE = "evaluations.npz"


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


def hyperparams_dir() -> Path:
    """Our hyperparameter files: beside the package in a checkout, under ``<prefix>/share/sb3-dipper`` when installed."""
    checkout = Path(__file__).resolve().parent.parent / "hyperparams"
    if checkout.is_dir():
        return checkout
    return Path(sys.prefix) / "share" / "sb3-dipper" / "hyperparams"


def sample_dipper_params(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """Optuna search space of DIPPER's higher level and option length (the lower SAC keeps its YAML settings)."""
    return {
        "value_reg_coef": trial.suggest_categorical("value_reg_coef", [0.0, 0.01, 0.1, 1.0]),
        **_sample_dipper_without_value_term(trial),
    }


def sample_dipper_nov_params(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """DIPPER's search space with the lower-value term off: DIPPER-No-V is DIPPER at lambda = 0, tuned or not."""
    return keep_params_without_value_term(_sample_dipper_without_value_term(trial))


def _sample_dipper_without_value_term(trial: optuna.Trial) -> dict[str, Any]:
    return {
        "learning_rate": trial.suggest_float("learning_rate", 1e-4, 3e-3, log=True),
        "beta": trial.suggest_float("beta", 0.01, 1.0, log=True),
        "nll_coef": trial.suggest_categorical("nll_coef", [0.0, 0.5, 1.0, 2.0]),
        "option_steps": trial.suggest_categorical("option_steps", [10, 15, 20, 25]),
        "pairs_per_batch": trial.suggest_categorical("pairs_per_batch", [32, 64, 128]),
        "random_subgoal_prob": trial.suggest_categorical("random_subgoal_prob", [0.0, 0.1, 0.2, 0.3]),
    }


def sample_hier_params(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """Optuna search space of HIER's higher SAC and option length."""
    return {
        "learning_rate": trial.suggest_float("learning_rate", 1e-4, 3e-3, log=True),
        "high_gamma": trial.suggest_categorical("high_gamma", [0.9, 0.95, 0.98]),
        "high_batch_size": trial.suggest_categorical("high_batch_size", [128, 256, 512]),
        "option_steps": trial.suggest_categorical("option_steps", [10, 15, 20, 25]),
        "random_subgoal_prob": trial.suggest_categorical("random_subgoal_prob", [0.0, 0.1, 0.2, 0.3]),
    }


def sample_piper_params(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """HIER's search space plus PIPER's reward model and the weight of the lower-value term in its labels."""
    return {
        **sample_hier_params(trial, n_actions, n_envs, additional_args),
        "reward_learning_rate": trial.suggest_float("reward_learning_rate", 1e-4, 3e-3, log=True),
        "reward_batch_size": trial.suggest_categorical("reward_batch_size", [25, 50, 100]),
        "value_reg_coef": trial.suggest_categorical("value_reg_coef", [0.0, 1e-6, 1e-3, 0.1]),
    }


def sample_saga_params(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """HIER's search space plus the weight of SAGA's adversarial term and its discriminator's learning rate."""
    return {
        **sample_hier_params(trial, n_actions, n_envs, additional_args),
        "adversarial_coef": trial.suggest_float("adversarial_coef", 1e-4, 1e-1, log=True),
        "discriminator_learning_rate": trial.suggest_float("discriminator_learning_rate", 1e-4, 1e-3, log=True),
    }


def sample_dpo_flat_params(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """Optuna search space of DPO-FLAT: its DPO loss, segment length and batch of pairs."""
    return {
        "learning_rate": trial.suggest_float("learning_rate", 1e-4, 3e-3, log=True),
        "beta": trial.suggest_float("beta", 0.01, 1.0, log=True),
        "nll_coef": trial.suggest_categorical("nll_coef", [0.0, 0.5, 1.0]),
        "segment_length": trial.suggest_categorical("segment_length", [10, 15, 20, 25]),
        "pairs_per_batch": trial.suggest_categorical("pairs_per_batch", [32, 50, 64, 128]),
        "random_action_prob": trial.suggest_categorical("random_action_prob", [0.0, 0.1, 0.2, 0.3]),
    }


def keep_params(params: dict[str, Any]) -> dict[str, Any]:
    """Our samplers return constructor kwargs directly, so a stored trial converts to itself."""
    return dict(params)


def keep_params_without_value_term(params: dict[str, Any]) -> dict[str, Any]:
    """DIPPER-No-V's converter: a stored trial, even one of a DIPPER study, trains with ``value_reg_coef = 0``."""
    return {**params, "value_reg_coef": 0.0}


SAMPLERS = {"dipper": sample_dipper_params, "dipper_paper": sample_dipper_params, "dipper_nov": sample_dipper_nov_params}
SAMPLERS.update(hier=sample_hier_params, piper=sample_piper_params, saga=sample_saga_params)
# HAC and RAPS are tuned over HIER's space: the higher SAC and the option length.
SAMPLERS.update(hac=sample_hier_params, raps=sample_hier_params, dpo_flat=sample_dpo_flat_params)


def register(control: RunControl | None = None) -> None:
    """Make rl-zoo3 know our algorithms, samplers and env ids, and give each run its own folder (idempotent).

    :param control: how ``train`` pauses or resumes (default: neither)
    """
    import gymnasium as gym
    import gymnasium_robotics
    import rl_zoo3
    from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER

    gym.register_envs(gymnasium_robotics)
    rl_zoo3.ALGOS.update(ZOO_ALGORITHMS)
    HYPERPARAMS_SAMPLER.update(SAMPLERS)
    HYPERPARAMS_CONVERTER.update({name: keep_params for name in SAMPLERS})  # type: ignore[misc]
    HYPERPARAMS_CONVERTER["dipper_nov"] = keep_params_without_value_term  # type: ignore[assignment]
    # DAC is SAC with a learned reward: the zoo's own SAC search space and its converter apply unchanged.
    HYPERPARAMS_SAMPLER["dac"] = HYPERPARAMS_SAMPLER["sac"]
    HYPERPARAMS_CONVERTER["dac"] = HYPERPARAMS_CONVERTER["sac"]
    _install_run_folder_claim(control)


# The subcommands of `sb3-dipper-zoo`: each one's rl-zoo3 module and its help line. A command runs the module's function
# of the command's name, as rl_zoo3.cli does, except record_video, a module run as a script. Each command imports only
# its own module: through rl_zoo3.cli the plotting modules (seaborn) would add seconds to every `train` and `enjoy`.
COMMANDS = {
    "train": ("rl_zoo3.train", "train an agent (rl-zoo3's train; --conf-file defaults to our hyperparams/<algo>.yml)"),
    "enjoy": ("rl_zoo3.enjoy", "run a trained agent (rl-zoo3's enjoy)"),
    "record_video": ("rl_zoo3.record_video", "record a video of a trained agent (rl-zoo3's record_video)"),
    "plot_train": ("rl_zoo3.plots.plot_train", "plot training curves (rl-zoo3's plot_train)"),
    "plot_from_file": ("rl_zoo3.plots.plot_from_file", "plot from a post-processed results file (rl-zoo3's plot_from_file)"),
    "all_plots": ("rl_zoo3.plots.all_plots", "plot evaluation results of several runs (rl-zoo3's all_plots)"),
}


def command_parser() -> argparse.ArgumentParser:
    """The parser of ``sb3-dipper-zoo COMMAND``: usage and help; each command parses its own flags."""
    parser = argparse.ArgumentParser(
        prog="sb3-dipper-zoo",
        description="rl-zoo3's command line with the sb3-dipper algorithms (" + ", ".join(ZOO_ALGORITHMS) + ").",
        epilog="Run `sb3-dipper-zoo COMMAND --help` for the flags of a command: rl-zoo3's own, and for train also "
        "--pause-after-minutes, --resume and --label-page.",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for command, (_, description) in COMMANDS.items():
        # Each command parses its own flags: here they only show in `COMMAND --help`, which the command prints.
        commands.add_parser(command, help=description, add_help=False)
    return parser


def _zoo_flags(argv: list[str]) -> argparse.Namespace:
    """The flags of rl-zoo3's train, enjoy and record_video that we read, parsed the way their parsers do.

    argparse accepts ``--algo dipper``, ``--algo=dipper`` and abbreviations such as ``--alg dipper``; a parser with the
    same option strings reads all of them alike. Everything else is left to rl-zoo3, which also reports malformed flags
    (then nothing is read here).
    """
    parser = argparse.ArgumentParser(add_help=False, exit_on_error=False)
    parser.add_argument("--algo")
    parser.add_argument("--env")
    parser.add_argument("-conf", "--conf-file")
    try:
        flags, _ = parser.parse_known_args(argv)
    except argparse.ArgumentError:
        return argparse.Namespace(algo=None, env=None, conf_file=None)
    return flags


def zoo_argv(command: str, argv: list[str]) -> list[str]:
    """rl-zoo3's flags for ``command``, with our defaults added.

    - ``--env module:EnvId`` (gymnasium's form, which imports ``module`` to register the id) becomes ``--env EnvId``
      after that import: rl-zoo3 looks plain ids up in gymnasium's registry and names run folders after them.
    - ``train`` reads our ``hyperparams/<algo>.yml`` unless ``--conf-file`` is given; for an env without an entry there,
      rl-zoo3 uses its ``default`` entry (the paper-scale profile for any goal env).

    Added flags go last: argparse keeps the last value of a repeated flag. The plot commands' flags pass unchanged
    (their ``--env`` names run folders, several at a time).

    :param command: the ``sb3-dipper-zoo`` subcommand
    :param argv: its flags
    """
    if command not in ("train", "enjoy", "record_video"):
        return argv
    flags = _zoo_flags(argv)
    added: list[str] = []
    if flags.env is not None and ":" in flags.env:
        module, _, env_id = flags.env.partition(":")
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as error:
            raise ModuleNotFoundError(
                f"--env {flags.env}: the module {module!r} that should register {env_id!r} cannot be imported ({error}). "
                "Install it, or pass a registered env id without the `module:` prefix."
            ) from error
        added += ["--env", env_id]
    ours = hyperparams_dir() / f"{flags.algo}.yml"
    if command == "train" and flags.algo is not None and flags.conf_file is None and ours.exists():
        added += ["--conf-file", str(ours)]
    return [*argv, *added]


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
        run's whole budget
    :param label_page: ``--label-page [HOST:]PORT``: serve the labelling page of the model's label queue (its
        ``preference_source`` is ``people:DIR`` or ``mixed:DIR:FRACTION``) while it trains, as ``(host, port)``
    """

    pause_after_minutes: float | None = None
    resume: Path | None = None
    label_page: tuple[str, int] | None = None

    def check_resumable(self, env_name: str, hyperparameters: Mapping[str, Any]) -> None:
        """With ``--resume``, refuse before anything changes a run that cannot continue as it was: other
        hyperparameters than the run's own (:func:`check_resumed_hyperparameters`), or a damaged evaluation record.

        :param env_name: the env's folder name in the run folder
        :param hyperparameters: the hyperparameters given, as rl-zoo3 read them
        """
        if self.resume is None:
            return
        check_resumed_hyperparameters(self.resume, env_name, hyperparameters)
        recorded_evaluations(self.resume)


def parse_label_page(text: str) -> tuple[str, int]:
    """``--label-page``'s ``[HOST:]PORT`` as ``(host, port)``; the host defaults to this machine only."""
    host, _, port = text.rpartition(":")
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"--label-page takes [HOST:]PORT, for example 5000 or 0.0.0.0:5000 (0: a free port), got {text!r}")
    return host or "127.0.0.1", int(port)


def run_control_parser() -> argparse.ArgumentParser:
    """The flags ``sb3-dipper-zoo train`` adds to rl-zoo3's: read by :func:`split_run_control`, listed by ``--help``."""
    parser = argparse.ArgumentParser(prog="sb3-dipper-zoo train", usage=argparse.SUPPRESS, add_help=False, exit_on_error=False)
    flags = parser.add_argument_group(
        "sb3-dipper-zoo train's own flags",
        "On top of rl-zoo3's flags above. --conf-file defaults to sb3-dipper's hyperparams/<algo>.yml, and --env also "
        "takes gymnasium's module:EnvId form.",
    )
    flags.add_argument(
        "--pause-after-minutes",
        type=float,
        metavar="M",
        help="after M minutes of training, save a resume checkpoint in the run folder and stop",
    )
    flags.add_argument(
        "--resume",
        type=Path,
        metavar="RUN_FOLDER",
        help="continue the run paused in RUN_FOLDER to its whole budget (give the same other flags)",
    )
    flags.add_argument(
        "--label-page",
        metavar="[HOST:]PORT",
        help="serve the labelling page of the model's label queue (preference_source 'people:DIR') while it trains "
        "(port 0: a free port); sb3-dipper-label --run DIR serves it after training",
    )
    return parser


def asks_for_help(argv: list[str]) -> bool:
    """Whether ``argv`` holds ``-h`` or ``--help`` (or an abbreviation, such as ``--he``, that argparse takes for it)."""
    parser = argparse.ArgumentParser(add_help=False, exit_on_error=False)
    parser.add_argument("-h", "--help", action="store_true")
    try:
        return parser.parse_known_args(argv)[0].help
    except argparse.ArgumentError:
        return False


def print_train_help() -> None:
    """``sb3-dipper-zoo train --help``: rl-zoo3's train flags (with our algorithms among ``--algo``'s), then ours."""
    import rl_zoo3.train

    register()
    sys.argv = ["sb3-dipper-zoo train", "--help"]
    try:
        rl_zoo3.train.train()
    except SystemExit as exit_:  # argparse exits once it has printed the help
        if exit_.code not in (0, None):
            raise
    print()
    print(run_control_parser().format_help(), end="", flush=True)


def split_run_control(argv: list[str]) -> tuple[RunControl, list[str]]:
    """Our flags out of ``train``'s argv (rl-zoo3 would refuse them), with checks that name the flag and the fix."""
    try:
        flags, rest = run_control_parser().parse_known_args(argv)
    except argparse.ArgumentError as error:
        raise ValueError(f"sb3-dipper-zoo train: {error}") from None
    if flags.pause_after_minutes is not None and not flags.pause_after_minutes >= 0:
        raise ValueError(f"--pause-after-minutes must be >= 0 minutes, got {flags.pause_after_minutes}")
    if flags.resume is not None and not (flags.resume / RESUME_FOLDER / RESUME_MODEL).is_file():
        raise FileNotFoundError(
            f"--resume {flags.resume}: no resume checkpoint {flags.resume / RESUME_FOLDER / RESUME_MODEL}. Resume a run "
            "folder that a run started with --pause-after-minutes paused in."
        )
    label_page = None if flags.label_page is None else parse_label_page(flags.label_page)
    return RunControl(flags.pause_after_minutes, flags.resume, label_page), rest


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


@dataclass(frozen=True)
class RecordedObject:
    """A Python object in a hyperparameter record (``!!python/name:torch.nn.ReLU``), kept as its tag and value."""

    tag: str
    value: Any

    def __repr__(self) -> str:
        return f"!!python/{self.tag}{'' if self.value in ('', None) else f' {self.value!r}'}"


class _RecordLoader(yaml.SafeLoader):
    """YAML's safe loader, reading the Python tags that rl-zoo3's ``yaml.dump`` writes into ``config.yml`` without
    building any object: an ``OrderedDict`` becomes a dict, a tuple a tuple, anything else a :class:`RecordedObject`
    (enough to compare two records)."""


def _recorded_ordered_dict(loader: yaml.SafeLoader, node: yaml.Node) -> dict[Any, Any]:
    (pairs,) = loader.construct_sequence(node, deep=True)  # type: ignore[arg-type]
    return {key: value for key, value in pairs}


def _recorded_tuple(loader: yaml.SafeLoader, node: yaml.Node) -> tuple[Any, ...]:
    return tuple(loader.construct_sequence(node, deep=True))  # type: ignore[arg-type]


def _recorded_object(loader: yaml.SafeLoader, tag: str, node: yaml.Node) -> RecordedObject:
    if isinstance(node, yaml.MappingNode):
        return RecordedObject(tag, loader.construct_mapping(node, deep=True))
    if isinstance(node, yaml.SequenceNode):
        return RecordedObject(tag, tuple(loader.construct_sequence(node, deep=True)))
    return RecordedObject(tag, loader.construct_scalar(node))  # type: ignore[arg-type]


_RecordLoader.add_constructor("tag:yaml.org,2002:python/object/apply:collections.OrderedDict", _recorded_ordered_dict)
_RecordLoader.add_constructor("tag:yaml.org,2002:python/tuple", _recorded_tuple)
_RecordLoader.add_multi_constructor("tag:yaml.org,2002:python/", _recorded_object)


def as_recorded(hyperparameters: Mapping[str, Any]) -> dict[str, Any]:
    """``hyperparameters`` as rl-zoo3 records them in ``config.yml`` (``yaml.dump``) and :func:`recorded_hyperparameters`
    reads them back, so that given and recorded ones compare alike."""
    return yaml.load(yaml.dump(dict(hyperparameters)), Loader=_RecordLoader)


def recorded_hyperparameters(config: Path) -> dict[str, Any]:
    """The hyperparameters rl-zoo3 recorded in a run's ``config.yml``, read without running code."""
    try:
        record = yaml.load(config.read_text(), Loader=_RecordLoader)
    except FileNotFoundError:
        raise FileNotFoundError(
            f"{config} is missing: rl-zoo3 writes the hyperparameters a run starts with there, and --resume checks the "
            "ones given against them. Restore it from a copy of the run folder, or start a new run (without --resume)."
        ) from None
    except yaml.YAMLError as error:
        raise ValueError(
            f"Malformed hyperparameter record {config}: {error}. Restore it from a copy of the run folder."
        ) from error
    if not isinstance(record, dict):
        raise ValueError(f"Malformed hyperparameter record {config}: expected a mapping of hyperparameters")
    return record


def differing_hyperparameters(started: Mapping[str, Any], given: Mapping[str, Any]) -> list[tuple[str, Any, Any]]:
    """``(name, started with, given)`` for every hyperparameter that differs (``None`` for one not set), by name.

    A ``use_sde`` entry in a recorded ``*policy_kwargs`` dict that the given one lacks is no difference: SB3's SAC
    writes its ``use_sde`` into the ``policy_kwargs`` it is handed, and rl-zoo3 records that dict after the model is
    built (sb3-dipper's hierarchical algorithms handed theirs to SAC too before they copied it).
    """
    differing = []
    for name in sorted(set(started) | set(given)):
        recorded, wanted = started.get(name), given.get(name)
        if name.endswith("policy_kwargs") and isinstance(recorded, dict) and isinstance(wanted, dict):
            if "use_sde" in recorded and "use_sde" not in wanted:
                recorded = {key: value for key, value in recorded.items() if key != "use_sde"}
        if recorded != wanted:
            differing.append((name, started.get(name), given.get(name)))
    return differing


def check_resumed_hyperparameters(run_folder: Path, env_name: str, given: Mapping[str, Any]) -> None:
    """Refuse to resume a run with hyperparameters (YAML entry, ``-params``, Optuna trial) other than its own.

    rl-zoo3 hands the hyperparameters given to ``load``, which sets them on the model: a resumed run would continue
    with new values and save them into its next checkpoint, a different experiment under the same run folder.

    :param run_folder: the run folder given to ``--resume``
    :param env_name: the env's folder name in the run folder, where rl-zoo3 writes ``config.yml``
    :param given: the hyperparameters of this command, as rl-zoo3 records them
    """
    config = run_folder / env_name / CONFIG_FILE
    # A run started with the lower level's bc_coef: 0.02 resumes with demo_kwargs: {bc_coef: 0.02}, the same setting.
    recorded = (recorded_hyperparameters(config), as_recorded(given))
    started, wanted = (in_new_form(hyperparameters, ZOO_ALGORITHMS.values()) for hyperparameters in recorded)
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
    arrays = read_npz(path, "evaluation record", fix)
    missing = [key for key in ("timesteps", "results", "ep_lengths") if key not in arrays]
    if missing:
        raise ValueError(f"Malformed evaluation record {path}: missing {missing}. {fix}")
    return arrays


def set_aside_part(run_folder: Path) -> None:
    """Move the monitor files and ``progress.csv`` of the part trained so far into ``<run>/part_<k>/``.

    The resumed part writes its own (both are created afresh, ``progress.csv`` exclusively); ``zoo_scripts/plot.py``
    reads the ``progress.csv`` and the monitor files of every part in order. A part killed after its last checkpoint
    logged steps and episodes the resumed run trains again: those ``progress.csv`` rows (by step) and monitor episodes
    (those that ended after the checkpoint was written) are dropped, so every step and episode is logged once.
    """
    logs = [*run_folder.glob("*.monitor.csv"), *run_folder.glob("progress.csv")]
    if not logs:
        return
    part = run_folder / f"part_{1 + len(list(run_folder.glob('part_*')))}"
    part.mkdir()
    for path in logs:
        path.rename(part / path.name)
    progress = part / "progress.csv"
    if progress.exists() and progress.stat().st_size > 0:
        rows = pd.read_csv(progress)
        if STEPS_KEY in rows:
            rows[rows[STEPS_KEY] <= checkpoint_steps(run_folder)].to_csv(progress, index=False)
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


def start_label_page(model: BaseAlgorithm, host: str, port: int) -> Any:
    """``--label-page``: serve the labelling page of ``model``'s label queue from this process while it trains.

    :return: the running server (``shutdown()`` stops it)
    """
    directory = label_queue_directory(getattr(model, "preference_source", None))
    if directory is None:
        raise ValueError(
            f"--label-page: {type(model).__name__}'s preference_source sends no pairs to people, so there is nothing "
            "to label. Train with -params \"preference_source:'people:DIR'\" (or 'mixed:DIR:FRACTION'), or leave "
            "out --label-page."
        )
    try:
        from sb3_dipper.labelling.app import serve_in_background
    except ImportError as error:
        raise ImportError(f"--label-page needs the labelling page's packages: pip install -e '.[label]' ({error})") from error
    server = serve_in_background(directory, host, port)
    # The only way to tell the person at the terminal where the page is (rl-zoo3 prints its own progress too).
    print(f"Labelling page of {directory}: http://{host}:{server.server_port}", flush=True)
    return server


def _install_run_folder_claim(control: RunControl | None = None) -> None:
    """Make rl-zoo3's train create each run's folder with :func:`claim_run_folder` and obey ``control``.

    :param control: ``--pause-after-minutes`` and ``--resume`` (idempotent: the last call's control counts)
    """
    import rl_zoo3.train
    from rl_zoo3.exp_manager import ExperimentManager
    from rl_zoo3.utils import get_latest_run_id

    run_control = control or RunControl()

    class OwnRunFolderExperimentManager(ExperimentManager):
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

        def read_hyperparameters(self) -> tuple[dict[str, Any], dict[str, Any]]:
            hyperparams, saved_hyperparams = super().read_hyperparameters()
            # Before anything in the run folder changes (create_log_folder sets the last part's logs aside).
            run_control.check_resumable(str(self.env_name), saved_hyperparams)
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


def main() -> None:
    """``sb3-dipper-zoo {train,enjoy,record_video,plot_train,plot_from_file,all_plots} ...``: rl-zoo3's CLI, our algorithms."""
    command = command_parser().parse_args(sys.argv[1:2]).command
    if command == "train" and asks_for_help(sys.argv[2:]):
        # Before our flags are checked: a help request is answered whatever else the command line holds.
        print_train_help()
        return
    control, argv = split_run_control(sys.argv[2:]) if command == "train" else (RunControl(), sys.argv[2:])
    register(control)
    argv = zoo_argv(command, argv)
    # rl-zoo3's parsers name the program after sys.argv[0]: their usage lines then read `sb3-dipper-zoo train ...`.
    sys.argv = [f"sb3-dipper-zoo {command}", *argv]
    module = COMMANDS[command][0]
    if command == "record_video":
        runpy.run_module(module, run_name="__main__")
    else:
        getattr(importlib.import_module(module), command)()


if __name__ == "__main__":
    main()
