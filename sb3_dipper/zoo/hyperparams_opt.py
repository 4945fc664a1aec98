"""Optuna search spaces of our algorithms for rl-zoo3's ``-optimize``, registered by :func:`sb3_dipper.zoo.register`.

rl-zoo3 looks a sampler up by zoo name in its ``HYPERPARAMS_SAMPLER`` table and converts a stored trial back into
hyperparameters with its ``HYPERPARAMS_CONVERTER`` table; :data:`SAMPLERS` and :data:`CONVERTERS` fill both.

A DIPPER trial samples one of its switches, ``switch_kwargs["nll_coef"]``; the experiment manager
(:mod:`sb3_dipper.zoo.exp_manager`) keeps the entry's other switches, so that a trial changes only what it samples.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import optuna

from sb3_dipper.common.deprecation import in_new_form
from sb3_dipper.dipper import DIPPER


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
        # Optuna's name is the switch's: a study's trials before switch_kwargs convert alike (dipper_trial_params).
        "switch_kwargs": {"nll_coef": trial.suggest_categorical("nll_coef", [0.0, 0.5, 1.0, 2.0])},
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


def dipper_trial_params(params: dict[str, Any]) -> dict[str, Any]:
    """DIPPER's converter: a stored trial's switches (Optuna names them as the parameters they were, ``nll_coef``) in
    ``switch_kwargs``."""
    return in_new_form(params, [DIPPER])


def keep_params_without_value_term(params: dict[str, Any]) -> dict[str, Any]:
    """DIPPER-No-V's converter: a stored trial, even one of a DIPPER study, trains with ``value_reg_coef = 0``."""
    return {**dipper_trial_params(params), "value_reg_coef": 0.0}


SAMPLERS = {"dipper": sample_dipper_params, "dipper_paper": sample_dipper_params, "dipper_nov": sample_dipper_nov_params}
SAMPLERS.update(hier=sample_hier_params, piper=sample_piper_params, saga=sample_saga_params)
# HAC and RAPS are tuned over HIER's space: the higher SAC and the option length.
SAMPLERS.update(hac=sample_hier_params, raps=sample_hier_params, dpo_flat=sample_dpo_flat_params)

CONVERTERS: dict[str, Callable[[dict[str, Any]], dict[str, Any]]] = {name: keep_params for name in SAMPLERS}
CONVERTERS.update(dipper=dipper_trial_params, dipper_paper=dipper_trial_params, dipper_nov=keep_params_without_value_term)
