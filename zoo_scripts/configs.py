"""Read our RL-Zoo hyperparameter files (``hyperparams/<algo>.yml``) without importing rl-zoo3.

The demo and the in-process benchmarks (``benchmark.py throughput`` and ``profiles``) build models from the same YAML
entries the zoo trains with, so there is one source of configuration; ``benchmark.py learning`` runs the zoo itself.
Strings such as ``"dict(net_arch=[64, 64])"`` are evaluated as rl-zoo3 does, with the few names its files use and no
builtins.
"""

from __future__ import annotations

import argparse
import json
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch as th
import yaml
from sb3_contrib import TQC
from stable_baselines3 import SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecEnv, VecNormalize
from stable_baselines3.her.her_replay_buffer import HerReplayBuffer

from sb3_dipper.common.files import write_bytes_atomically
from sb3_dipper.common.validation import check_keyword_arguments
from sb3_dipper.zoo import ZOO_ALGORITHMS

HYPERPARAMS_DIR = Path(__file__).resolve().parent.parent / "hyperparams"

ALGORITHMS: dict[str, type[BaseAlgorithm]] = {**ZOO_ALGORITHMS, "sac": SAC, "tqc": TQC}

# The zoo's own keys: they configure the env and the run, not the algorithm's constructor.
ZOO_KEYS = ("n_timesteps", "n_envs", "normalize", "env_kwargs", "monitor_kwargs", "env_wrapper", "callback", "frame_stack")
EVALUATED_KEYS = (
    "policy_kwargs",
    "low_policy_kwargs",
    "replay_buffer_kwargs",
    "high_replay_buffer_kwargs",
    "monitor_kwargs",
    "normalize",
)
NAMESPACE = {"dict": dict, "nn": th.nn, "th": th, "HerReplayBuffer": HerReplayBuffer}


def load_entry(algo: str, env_id: str, hyperparams_dir: Path = HYPERPARAMS_DIR) -> dict[str, Any]:
    """The entry for ``env_id`` (or ``default``) of ``<algo>.yml``, with string values evaluated as rl-zoo3 does."""
    path = hyperparams_dir / f"{algo}.yml"
    with open(path) as file:
        entries = yaml.safe_load(file)
    if env_id not in entries and "default" not in entries:
        raise KeyError(f"{path} has no entry for {env_id!r} and no 'default' entry")
    entry = dict(entries.get(env_id, entries.get("default")))
    for key in EVALUATED_KEYS:
        if isinstance(entry.get(key), str):
            entry[key] = eval(entry[key], {"__builtins__": {}}, NAMESPACE)
    if isinstance(entry.get("replay_buffer_class"), str):
        entry["replay_buffer_class"] = NAMESPACE[entry["replay_buffer_class"]]
    return entry


def make_model(
    algo: str,
    env_id: str,
    seed: int,
    overrides: dict[str, Any] | None = None,
    hyperparams: Path = HYPERPARAMS_DIR,
    **model_kwargs: Any,
) -> tuple[BaseAlgorithm, VecEnv, int]:
    """Build the training env and the model of one YAML entry of ``hyperparams/<algo>.yml``.

    :param hyperparams: the folder of the YAML files (``hyperparams/paper`` for the paper-scale settings)
    :return: ``(model, env, n_timesteps)``
    """
    entry = {**load_entry(algo, env_id, hyperparams), **(overrides or {})}
    env = make_env(env_id, entry, seed)
    n_timesteps = int(entry["n_timesteps"])
    kwargs = {key: value for key, value in entry.items() if key not in ZOO_KEYS}
    # Our algorithms check their keywords themselves; SB3's SAC and TQC would raise a bare TypeError for a misspelt key.
    check_keyword_arguments(ALGORITHMS[algo], {**kwargs, **model_kwargs}, f"{hyperparams / f'{algo}.yml'} or the overrides")
    model = ALGORITHMS[algo](env=env, seed=seed, **kwargs, **model_kwargs)
    return model, env, n_timesteps


def make_env(env_id: str, entry: dict[str, Any], seed: int, n_envs: int | None = None) -> VecEnv:
    """The vectorised env of an entry (``n_envs``, ``env_kwargs``, ``normalize``), Monitor recording ``is_success``."""
    env = make_vec_env(
        env_id,
        n_envs=n_envs or int(entry.get("n_envs", 1)),
        seed=seed,
        env_kwargs=entry.get("env_kwargs"),
        monitor_kwargs=entry.get("monitor_kwargs"),
    )
    normalize = entry.get("normalize", False)
    if normalize:
        env = VecNormalize(env, **(normalize if isinstance(normalize, dict) else {}))
    return env


class _ZooConfigLoader(yaml.SafeLoader):
    """Reads the ``config.yml`` rl-zoo3 saves in a run folder (an ``OrderedDict`` of the hyperparameters) as a dict,
    without constructing any other Python object."""


_ZooConfigLoader.add_constructor(
    "tag:yaml.org,2002:python/object/apply:collections.OrderedDict",
    lambda loader, node: dict(loader.construct_sequence(node, deep=True)[0]),  # type: ignore[arg-type]
)


def run_env_kwargs(run: Path, env_id: str) -> dict[str, Any] | None:
    """The ``env_kwargs`` a zoo run trained with (its ``<env>/config.yml``, the YAML entry with ``-params`` and
    ``--env-kwargs`` applied); ``None`` where the run saved no configuration or had none."""
    config = run / env_id / "config.yml"
    if not config.is_file():
        return None
    try:
        hyperparams = yaml.load(config.read_text(), Loader=_ZooConfigLoader)  # a SafeLoader: no objects built
    except yaml.YAMLError as error:
        raise ValueError(f"{config} is not the configuration rl-zoo3 saves: {error}") from error
    return hyperparams.get("env_kwargs") if isinstance(hyperparams, dict) else None


def trained_run(
    run: Path, algo: str, env_id: str, seed: int, n_envs: int = 1, model_file: Path | None = None
) -> tuple[BaseAlgorithm, VecEnv]:
    """The model of a zoo run folder (``<run>/<env>.zip``, or ``model_file``, e.g. one of its checkpoints) on a fresh
    evaluation env, with the run's ``VecNormalize`` statistics frozen where it has them.

    rl-zoo3 keeps one set of statistics per run (``<run>/<env>/vecnormalize.pkl``, written with the best and the
    final model), none per checkpoint. A hierarchical model carries its own copy of the statistics it trained with
    (its lower level's normaliser, refreshed at every step), so a checkpoint is measured with the statistics of its
    own step, not with those of a later or earlier save. The env takes the run's own ``env_kwargs`` (its episode length,
    for one), which may differ from today's YAML entry."""
    entry = {**load_entry(algo, env_id), "normalize": False}
    saved_env_kwargs = run_env_kwargs(run, env_id)
    if saved_env_kwargs is not None:
        entry["env_kwargs"] = saved_env_kwargs
    env = make_env(env_id, entry, seed=seed, n_envs=n_envs)
    statistics = run / env_id / "vecnormalize.pkl"
    if statistics.exists():
        env = VecNormalize.load(str(statistics), env)
        env.training, env.norm_reward = False, False
    model = ALGORITHMS[algo].load(model_file or run / f"{env_id}.zip", env=env)
    own = getattr(model, "low_normalizer", None)
    if isinstance(env, VecNormalize) and own is not None:
        own.restore(env)
    return model, env


def checkpoints(run: Path) -> list[Path]:
    """The checkpoints rl-zoo3 kept in ``run`` (``rl_model_<steps>_steps.zip``), in the order they were saved."""
    steps = {}
    for path in run.glob("rl_model_*_steps.zip"):
        match = re.fullmatch(r"rl_model_(\d+)_steps\.zip", path.name)
        if match:
            steps[path] = int(match.group(1))
    return sorted(steps, key=steps.__getitem__)


def measure_runs(
    parser: argparse.ArgumentParser,
    args: argparse.Namespace,
    measure: Callable[[Path, str, str, int, Path | None], tuple[int, dict[str, dict[str, float]]]],
    report: str,
    columns: tuple[str, str, str],
) -> None:
    """Measure every run of ``args.runs`` with ``measure(run, args.algo, env_id, args.episodes, model_file)``
    (``model_file`` ``None``: the run's final model, where it has one), also at every checkpoint the run kept with
    ``args.checkpoints``; print each result, write the final model's as ``<run>/<report>`` (JSON) and, with
    ``args.csv``, one CSV row per model and case.

    :param columns: the CSV's case column and its two metrics, e.g. ``("driver", "success", "options_reached")``
    """
    case_column, *metrics = columns
    rows = [",".join(("run", "steps", case_column, *metrics))]
    for run in args.runs:
        env_id = args.env or run.name.rsplit("_", 1)[0]
        models: list[Path | None] = list(checkpoints(run)) if args.checkpoints else []
        # A run still training (or paused) has checkpoints but no final model yet: measure what it has.
        if (run / f"{env_id}.zip").exists():
            models.append(None)
        if not models:
            parser.error(
                f"{run} has no final model ({env_id}.zip: the run has not finished)"
                + ("" if args.checkpoints else "; pass --checkpoints to measure the checkpoints it kept")
            )
        for model_file in models:
            try:
                steps, results = measure(run, args.algo, env_id, args.episodes, model_file)
            except ValueError as error:
                parser.error(str(error))
            if model_file is None:
                write_bytes_atomically(run / report, json.dumps(results, indent=1).encode())
            print(run, steps, json.dumps(results), flush=True)
            rows += [
                ",".join((str(run), str(steps), case, *(f"{result[metric]:.4f}" for metric in metrics)))
                for case, result in results.items()
            ]
    if args.csv is not None:
        write_bytes_atomically(args.csv, ("\n".join(rows) + "\n").encode())


def episode_successes(model: BaseAlgorithm, env: VecEnv, n_episodes: int, deterministic: bool = True) -> list[float]:
    """``info["is_success"]`` at the end of each of ``n_episodes`` evaluation episodes (deterministic by default)."""
    successes: list[float] = []

    def record(local_vars: dict[str, Any], _globals: dict[str, Any]) -> None:
        if local_vars["done"]:
            successes.append(float(local_vars["info"].get("is_success", 0.0)))

    evaluate_policy(model, env, n_eval_episodes=n_episodes, deterministic=deterministic, callback=record)
    return successes[:n_episodes]


def torch_threads() -> int:
    """One torch thread per run unless ``SB3_DIPPER_THREADS`` says otherwise (runs are small; processes parallelise)."""
    return int(os.environ.get("SB3_DIPPER_THREADS", "1"))
