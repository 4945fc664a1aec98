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
minutes of training and stops; ``--resume RUN_FOLDER`` (with the same other flags; ``-n`` may be left out) continues
that run in its folder to the budget it was started with: same step count, evaluations on the same grid appended to the
same ``evaluations.npz``, the replay buffers as they were. The resumed part reseeds its random generators, so it is not
the same run as one without a pause::

    sb3-dipper-zoo train --algo dipper --env FetchPushFixed-v0 -f logs --pause-after-minutes 80
    sb3-dipper-zoo train --algo dipper --env FetchPushFixed-v0 -f logs --resume logs/dipper/FetchPushFixed-v0_1

``--label-page [HOST:]PORT`` serves the labelling page (:mod:`sb3_dipper.labelling.app`) of the run's label queue from
the training process while it trains; the model's ``preference_source`` must send pairs to people::

    sb3-dipper-zoo train --algo dipper --env PointMazeFourRooms-v0 -params "preference_source:'people:logs/labels'" \
        --label-page 5000

That page stops when training ends; ``sb3-dipper-label --run logs/labels`` serves the queue on its own, for as long as
the person needs.

This module registers our algorithms into rl-zoo3 and holds the command line; the rest lives beside it, and every name
is importable from here too:

- :mod:`sb3_dipper.zoo.algorithms`: the zoo names of our algorithms and where their hyperparameter files are;
- :mod:`sb3_dipper.zoo.hyperparams_opt`: the Optuna search spaces of ``-optimize``;
- :mod:`sb3_dipper.zoo.callbacks`: the callback our hyperparameter files name (``progress.csv``) and the evaluation
  callback of every run (``evaluations.npz`` written whole);
- :mod:`sb3_dipper.zoo.exp_manager`: rl-zoo3's experiment manager with exclusive run folders, pausing, resuming and the
  labelling page (:func:`sb3_dipper.labelling.start_label_page`);
- :mod:`sb3_dipper.zoo.resume`: pausing and resuming long runs;
- :mod:`sb3_dipper.zoo.run_config`: the hyperparameter files and a run's recorded configuration, read without rl-zoo3.

rl-zoo3 patches gymnasium's ``TimeLimit`` when imported, so it is imported only when a command runs.
"""

from __future__ import annotations

import argparse
import importlib
import runpy
import sys
from pathlib import Path

from sb3_dipper.labelling.training_page import start_label_page
from sb3_dipper.zoo.algorithms import ZOO_ALGORITHMS, hyperparams_dir
from sb3_dipper.zoo.callbacks import AtomicEvalCallback, CSVProgressCallback
from sb3_dipper.zoo.exp_manager import RunControl, claim_run_folder, install_experiment_manager
from sb3_dipper.zoo.hyperparams_opt import (
    CONVERTERS,
    SAMPLERS,
    dipper_trial_params,
    keep_params,
    keep_params_without_value_term,
    sample_dipper_nov_params,
    sample_dipper_params,
    sample_dpo_flat_params,
    sample_hier_params,
    sample_piper_params,
    sample_saga_params,
)
from sb3_dipper.zoo.resume import (
    EVALUATIONS_FILE,
    RESUME_FOLDER,
    RESUME_MODEL,
    STEPS_KEY,
    PauseCheckpointCallback,
    check_resume_checkpoint,
    check_resumed_evaluations,
    check_resumed_hyperparameters,
    checkpoint_steps,
    continue_evaluations,
    differing_hyperparameters,
    drop_episodes_after,
    learn_resumed,
    recorded_evaluations,
    remove_resume_checkpoint,
    replace_folder,
    resumed_n_timesteps,
    run_env_folder,
    saved_steps,
    set_aside_part,
)
from sb3_dipper.zoo.run_config import ARGS_FILE, CONFIG_FILE, RecordedObject, as_recorded, recorded_hyperparameters

__all__ = [
    "ARGS_FILE",
    "COMMANDS",
    "CONFIG_FILE",
    "CONVERTERS",
    "EVALUATIONS_FILE",
    "RESUME_FOLDER",
    "RESUME_MODEL",
    "SAMPLERS",
    "STEPS_KEY",
    "ZOO_ALGORITHMS",
    "AtomicEvalCallback",
    "CSVProgressCallback",
    "PauseCheckpointCallback",
    "RecordedObject",
    "RunControl",
    "as_recorded",
    "asks_for_help",
    "check_resume_checkpoint",
    "check_resumed_evaluations",
    "check_resumed_hyperparameters",
    "checkpoint_steps",
    "claim_run_folder",
    "command_parser",
    "continue_evaluations",
    "differing_hyperparameters",
    "dipper_trial_params",
    "drop_episodes_after",
    "hyperparams_dir",
    "keep_params",
    "keep_params_without_value_term",
    "learn_resumed",
    "main",
    "parse_label_page",
    "print_train_help",
    "recorded_evaluations",
    "recorded_hyperparameters",
    "register",
    "remove_resume_checkpoint",
    "replace_folder",
    "resumed_n_timesteps",
    "run_control_parser",
    "run_env_folder",
    "sample_dipper_nov_params",
    "sample_dipper_params",
    "sample_dpo_flat_params",
    "sample_hier_params",
    "sample_piper_params",
    "sample_saga_params",
    "saved_steps",
    "set_aside_part",
    "split_run_control",
    "start_label_page",
    "zoo_argv",
]


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
    HYPERPARAMS_CONVERTER.update(CONVERTERS)  # type: ignore[arg-type]
    # DAC (SAC with a learned reward) and SACDemo (SAC with cloning) take the zoo's own SAC search space and converter.
    for name in ("dac", "sac_demo"):
        HYPERPARAMS_SAMPLER[name] = HYPERPARAMS_SAMPLER["sac"]
        HYPERPARAMS_CONVERTER[name] = HYPERPARAMS_CONVERTER["sac"]
    install_experiment_manager(control)


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
      rl-zoo3 uses its ``default`` entry (the CPU profile for any goal env).

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


def parse_label_page(text: str) -> tuple[str, int]:
    """``--label-page``'s ``[HOST:]PORT`` as ``(host, port)``; the host defaults to this machine only."""
    host, _, port = text.rpartition(":")
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(
            "--label-page takes [HOST:]PORT, for example 5000 or 127.0.0.1:5000 (0: a free port; from another machine, "
            f"forward the port over SSH), got {text!r}"
        )
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
        help="continue the run paused in RUN_FOLDER to the budget it was started with (give the same other flags; -n "
        "may be left out)",
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
        raise ValueError(str(error)) from None
    if flags.pause_after_minutes is not None and not flags.pause_after_minutes >= 0:
        raise ValueError(f"--pause-after-minutes must be >= 0 minutes, got {flags.pause_after_minutes}")
    if flags.resume is not None and not (flags.resume / RESUME_FOLDER / RESUME_MODEL).is_file():
        raise FileNotFoundError(
            f"--resume {flags.resume}: no resume checkpoint {flags.resume / RESUME_FOLDER / RESUME_MODEL}. Resume a run "
            "folder that a run started with --pause-after-minutes paused in."
        )
    label_page = None if flags.label_page is None else parse_label_page(flags.label_page)
    return RunControl(flags.pause_after_minutes, flags.resume, label_page), rest


def main() -> None:
    """``sb3-dipper-zoo {train,enjoy,record_video,plot_train,plot_from_file,all_plots} ...``: rl-zoo3's CLI, our algorithms."""
    if len(sys.argv) < 2:
        # Alone, the command lists its commands (with the usage-error status: nothing was run).
        command_parser().print_help()
        sys.exit(2)
    command = command_parser().parse_args(sys.argv[1:2]).command
    if command == "train" and asks_for_help(sys.argv[2:]):
        # Before our flags are checked: a help request is answered whatever else the command line holds.
        print_train_help()
        return
    try:
        control, argv = split_run_control(sys.argv[2:]) if command == "train" else (RunControl(), sys.argv[2:])
    except (ValueError, FileNotFoundError) as error:
        # A usage error, as argparse reports its own: one line and exit status 2, not a traceback.
        print(f"sb3-dipper-zoo {command}: error: {error}", file=sys.stderr)
        sys.exit(2)
    register(control)
    argv = zoo_argv(command, argv)
    # rl-zoo3's parsers name the program after sys.argv[0]: their usage lines then read `sb3-dipper-zoo train ...`.
    sys.argv = [f"sb3-dipper-zoo {command}", *argv]
    module = COMMANDS[command][0]
    if command == "record_video":
        runpy.run_module(module, run_name="__main__")
    else:
        getattr(importlib.import_module(module), command)()
