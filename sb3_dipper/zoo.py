"""RL-Zoo integration: our algorithms, their hyperparameter files and Optuna samplers, registered into rl-zoo3.

rl-zoo3 has no plugin mechanism; its documented recipe for external algorithms is to add them to ``rl_zoo3.ALGOS``
(and, for ``-optimize``, to its sampler and converter tables) before calling its entry points. ``sb3-dipper-zoo``
does that, then runs rl-zoo3's own CLI with its own flags:

    sb3-dipper-zoo train --algo dipper --env PointMazeFourRooms-v0 --seed 0
    sb3-dipper-zoo enjoy --algo dipper --env PointMazeFourRooms-v0 -f logs/ --no-render -n 2000
    sb3-dipper-zoo train --algo dipper --env PointMazeFourRooms-v0 -optimize --storage logs/dipper.log --study-name s1

For algorithms and envs this package has hyperparameters for, ``train`` reads ``hyperparams/<algo>.yml`` unless
``--conf-file`` is given. rl-zoo3 patches gymnasium's ``TimeLimit`` when imported, so it is imported only here.
"""

from __future__ import annotations

import runpy
import sys
import tempfile
from pathlib import Path
from typing import Any

import optuna
import yaml
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
    """

    def _init_callback(self) -> None:
        writer = self.training_env.get_attr("results_writer", indices=[0])[0]
        if writer is None:  # a Monitor without a file: nowhere to put progress.csv
            return
        folder = Path(writer.file_handler.name).parent
        self.model.logger.output_formats.append(CSVOutputFormat(str(folder / "progress.csv")))

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
        "learning_rate": trial.suggest_float("learning_rate", 1e-4, 3e-3, log=True),
        "beta": trial.suggest_float("beta", 0.01, 1.0, log=True),
        "value_reg_coef": trial.suggest_categorical("value_reg_coef", [0.0, 0.01, 0.1, 1.0]),
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


SAMPLERS = {"dipper": sample_dipper_params, "dipper_paper": sample_dipper_params, "dipper_nov": sample_dipper_params}
SAMPLERS.update(hier=sample_hier_params, piper=sample_piper_params, saga=sample_saga_params)
# HAC and RAPS are tuned over HIER's space: the higher SAC and the option length.
SAMPLERS.update(hac=sample_hier_params, raps=sample_hier_params, dpo_flat=sample_dpo_flat_params)


def register() -> None:
    """Make rl-zoo3 know our algorithms, samplers and env ids (idempotent)."""
    import gymnasium as gym
    import gymnasium_robotics
    import rl_zoo3
    from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER

    gym.register_envs(gymnasium_robotics)
    rl_zoo3.ALGOS.update(ZOO_ALGORITHMS)
    HYPERPARAMS_SAMPLER.update(SAMPLERS)
    HYPERPARAMS_CONVERTER.update({name: keep_params for name in SAMPLERS})  # type: ignore[misc]
    # DAC is SAC with a learned reward: the zoo's own SAC search space and its converter apply unchanged.
    HYPERPARAMS_SAMPLER["dac"] = HYPERPARAMS_SAMPLER["sac"]
    HYPERPARAMS_CONVERTER["dac"] = HYPERPARAMS_CONVERTER["sac"]


def _with_default_conf_file(argv: list[str]) -> list[str]:
    """Point ``train`` at our hyperparameter file of ``--algo`` unless the user chose one.

    rl-zoo3 only reads the entry named after the env id; for an env our file has no entry for, its ``default`` entry is
    written under that id to a temporary file, so any goal env trains with the paper-scale profile.
    """
    if not argv or argv[0] != "train" or any(flag in argv for flag in ("-conf", "--conf-file")):
        return argv
    algo, env_id = _flag_value(argv, "--algo", "-a"), _flag_value(argv, "--env")
    ours = hyperparams_dir() / f"{algo}.yml"
    if algo is None or not ours.exists():
        return argv
    with open(ours) as file:
        entries = yaml.safe_load(file)
    if env_id is None or env_id in entries or "default" not in entries:
        return [*argv, "--conf-file", str(ours)]
    with tempfile.NamedTemporaryFile("w", prefix=f"{algo}-", suffix=".yml", delete=False) as conf_file:
        yaml.safe_dump({env_id: entries["default"]}, conf_file)
    return [*argv, "--conf-file", conf_file.name]


def _flag_value(argv: list[str], *flags: str) -> str | None:
    for flag in flags:
        if flag in argv and argv.index(flag) + 1 < len(argv):
            return argv[argv.index(flag) + 1]
    return None


def main() -> None:
    """``sb3-dipper-zoo {train,enjoy,record_video,plot_train,plot_from_file,all_plots} ...``: rl-zoo3's CLI, our algorithms."""
    register()
    if sys.argv[1:2] == ["record_video"]:
        # rl-zoo3's video recorder is a module of its own, not a subcommand of its CLI.
        sys.argv = [sys.argv[0], *sys.argv[2:]]
        runpy.run_module("rl_zoo3.record_video", run_name="__main__")
        return
    from rl_zoo3.cli import main as zoo_main

    sys.argv = [sys.argv[0], *_with_default_conf_file(sys.argv[1:])]
    zoo_main()


if __name__ == "__main__":
    main()
