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
together with the same ``-f`` never share one. rl-zoo3 patches gymnasium's ``TimeLimit`` when imported, so it is
imported only here, and only when a command runs.
"""

from __future__ import annotations

import argparse
import importlib
import os
import runpy
import sys
from pathlib import Path
from typing import Any

import optuna
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import CSVOutputFormat

from sb3_dipper.dac import DAC
from sb3_dipper.dipper import DIPPER
from sb3_dipper.dpo_flat import DPOFlat
from sb3_dipper.hac import HAC
from sb3_dipper.hier import HIER
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
        "planning_lookahead": trial.suggest_categorical("planning_lookahead", [1, 2, 3]),
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


def register() -> None:
    """Make rl-zoo3 know our algorithms, samplers and env ids, and give each run its own folder (idempotent)."""
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
    _install_run_folder_claim()


# The subcommands of `sb3-dipper-zoo`: rl-zoo3's CLI scripts plus its video recorder, which is a module of its own.
COMMANDS = {
    "train": "train an agent (rl-zoo3's train; --conf-file defaults to our hyperparams/<algo>.yml)",
    "enjoy": "run a trained agent (rl-zoo3's enjoy)",
    "record_video": "record a video of a trained agent (rl-zoo3's record_video)",
    "plot_train": "plot training curves (rl-zoo3's plot_train)",
    "plot_from_file": "plot from a post-processed results file (rl-zoo3's plot_from_file)",
    "all_plots": "plot evaluation results of several runs (rl-zoo3's all_plots)",
}


def command_parser() -> argparse.ArgumentParser:
    """The parser of ``sb3-dipper-zoo COMMAND``: usage and help; each command parses its own flags."""
    parser = argparse.ArgumentParser(
        prog="sb3-dipper-zoo",
        description="rl-zoo3's command line with the sb3-dipper algorithms (" + ", ".join(ZOO_ALGORITHMS) + ").",
        epilog="Run `sb3-dipper-zoo COMMAND --help` for the flags of a command (they are rl-zoo3's own).",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for command, description in COMMANDS.items():
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


def _install_run_folder_claim() -> None:
    """Make rl-zoo3's train create each run's folder with :func:`claim_run_folder` (idempotent)."""
    import rl_zoo3.train
    from rl_zoo3.exp_manager import ExperimentManager
    from rl_zoo3.utils import get_latest_run_id

    class OwnRunFolderExperimentManager(ExperimentManager):
        """rl-zoo3's experiment manager whose run folder is claimed exclusively when it is created."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            # rl-zoo3's train passes its --uuid suffix by keyword.
            self.run_folder_suffix = kwargs.get("uuid_str", "")

        def create_log_folder(self) -> None:
            run_id = get_latest_run_id(self.log_path, self.env_name) + 1
            self.save_path = claim_run_folder(self.log_path, self.env_name, run_id, self.run_folder_suffix)
            self.params_path = f"{self.save_path}/{self.env_name}"
            super().create_log_folder()

    rl_zoo3.train.ExperimentManager = OwnRunFolderExperimentManager  # type: ignore[misc]


def main() -> None:
    """``sb3-dipper-zoo {train,enjoy,record_video,plot_train,plot_from_file,all_plots} ...``: rl-zoo3's CLI, our algorithms."""
    command = command_parser().parse_args(sys.argv[1:2]).command
    register()
    argv = zoo_argv(command, sys.argv[2:])
    # rl-zoo3's parsers name the program after sys.argv[0]: their usage lines then read `sb3-dipper-zoo train ...`.
    program = f"sb3-dipper-zoo {command}"
    if command == "record_video":
        # rl-zoo3's video recorder is a module of its own, not a subcommand of its CLI.
        sys.argv = [program, *argv]
        runpy.run_module("rl_zoo3.record_video", run_name="__main__")
        return
    from rl_zoo3.cli import main as zoo_main

    sys.argv = [program, command, *argv]
    zoo_main()


if __name__ == "__main__":
    main()
