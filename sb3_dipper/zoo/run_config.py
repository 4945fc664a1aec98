"""How a zoo run is configured, read without importing rl-zoo3: the entries of our hyperparameter files, the
hyperparameters rl-zoo3 recorded in a run folder, and the models and envs built from them as the zoo builds them.

- ``hyperparams/<algo>.yml`` (:func:`load_entry`, :func:`make_model`, :func:`make_env`): the demo and the in-process
  benchmarks build models from the same YAML entries the zoo trains with, so there is one source of configuration.
  Strings such as ``"dict(net_arch=[64, 64])"`` are evaluated as rl-zoo3 does, with the few names its files use and
  no builtins.
- ``<run>/<env>/config.yml`` (:func:`recorded_hyperparameters`): the hyperparameters a run started with, as rl-zoo3
  records them (``yaml.dump`` of an ``OrderedDict``, with Python tags), read by one safe loader
  (:class:`RecordLoader`) for both the resume check (``sb3-dipper-zoo train --resume``) and :func:`trained_run`.
- :func:`trained_run` and :func:`checkpoints`: a finished or paused run's models on a fresh evaluation env, the env
  made with the run's own ``env_kwargs``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch as th
import yaml
from sb3_contrib import TQC
from stable_baselines3 import SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecEnv, VecNormalize
from stable_baselines3.her.her_replay_buffer import HerReplayBuffer

from sb3_dipper.common.validation import check_keyword_arguments
from sb3_dipper.zoo.algorithms import ZOO_ALGORITHMS, hyperparams_dir

HYPERPARAMS_DIR = hyperparams_dir()

# Our algorithms under their zoo names, and SB3's and sb3-contrib's whose entries our files hold too.
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

# What rl-zoo3 records in <run folder>/<env>/ when a run starts: its hyperparameters (and its flags in args.yml).
CONFIG_FILE = "config.yml"
ARGS_FILE = "args.yml"


def yaml_entry(path: str | Path, env_id: str) -> dict[str, Any]:
    """The entry rl-zoo3 reads for ``env_id`` from the hyperparameter file ``path``: the env's own, else ``default``;
    its values as written."""
    with open(path) as file:
        entries = yaml.safe_load(file)
    if env_id not in entries and "default" not in entries:
        raise KeyError(f"{path} has no entry for {env_id!r} and no 'default' entry")
    return dict(entries.get(env_id, entries.get("default")))


def load_entry(algo: str, env_id: str, hyperparams_dir: Path = HYPERPARAMS_DIR) -> dict[str, Any]:
    """The entry for ``env_id`` (or ``default``) of ``<algo>.yml``, with string values evaluated as rl-zoo3 does."""
    entry = yaml_entry(hyperparams_dir / f"{algo}.yml", env_id)
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

    :param algo: the zoo name of the algorithm (a key of :data:`ALGORITHMS`)
    :param env_id: the env, and the entry of the YAML file (else its ``default`` entry)
    :param seed: the seed of the env and the model
    :param overrides: entries that replace the YAML's
    :param hyperparams: the folder of the YAML files (``hyperparams/paper`` for the paper-scale settings)
    :param model_kwargs: further keyword arguments of the algorithm's constructor
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


@dataclass(frozen=True)
class RecordedObject:
    """A Python object in a hyperparameter record (``!!python/name:torch.nn.ReLU``), kept as its tag and value."""

    tag: str
    value: Any

    def __repr__(self) -> str:
        return f"!!python/{self.tag}{'' if self.value in ('', None) else f' {self.value!r}'}"


class RecordLoader(yaml.SafeLoader):
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


RecordLoader.add_constructor("tag:yaml.org,2002:python/object/apply:collections.OrderedDict", _recorded_ordered_dict)
RecordLoader.add_constructor("tag:yaml.org,2002:python/tuple", _recorded_tuple)
RecordLoader.add_multi_constructor("tag:yaml.org,2002:python/", _recorded_object)


def as_recorded(hyperparameters: Mapping[str, Any]) -> dict[str, Any]:
    """``hyperparameters`` as rl-zoo3 records them in ``config.yml`` (``yaml.dump``) and :func:`recorded_hyperparameters`
    reads them back, so that given and recorded ones compare alike."""
    return yaml.load(yaml.dump(dict(hyperparameters)), Loader=RecordLoader)


def recorded_hyperparameters(config: Path) -> dict[str, Any]:
    """The hyperparameters rl-zoo3 recorded in a run's ``config.yml``, read without running code.

    :raises FileNotFoundError: there is no ``config``
    :raises ValueError: ``config`` is not such a record (not YAML, or not a mapping of hyperparameters)
    """
    text = config.read_text()
    try:
        record = yaml.load(text, Loader=RecordLoader)
    except yaml.YAMLError as error:
        raise ValueError(
            f"{config} is not the configuration rl-zoo3 saves: {error}. Restore it from a copy of the run folder."
        ) from error
    if not isinstance(record, dict):
        raise ValueError(
            f"{config} is not the configuration rl-zoo3 saves: expected a mapping of hyperparameters. Restore it from a "
            "copy of the run folder."
        )
    return record


def run_env_kwargs(run: Path, env_id: str) -> dict[str, Any] | None:
    """The ``env_kwargs`` a zoo run trained with (its ``<env>/config.yml``, the YAML entry with ``-params`` and
    ``--env-kwargs`` applied); ``None`` where the run saved no configuration or had none."""
    config = run / env_id / CONFIG_FILE
    if not config.is_file():
        return None
    return recorded_hyperparameters(config).get("env_kwargs")


def trained_run(
    run: Path, algo: str, env_id: str, seed: int, n_envs: int = 1, model_file: Path | None = None
) -> tuple[BaseAlgorithm, VecEnv]:
    """The model of a zoo run folder (``<run>/<env>.zip``, or ``model_file``, e.g. one of its checkpoints) on a fresh
    evaluation env, with the run's ``VecNormalize`` statistics frozen where it has them.

    rl-zoo3 keeps one set of statistics per run (``<run>/<env>/vecnormalize.pkl``, written with the best and the
    final model), none per checkpoint. A hierarchical model carries its own copy of the statistics it trained with
    (its lower level's normaliser, refreshed at every step), so a checkpoint is measured with the statistics of its
    own step, not with those of a later or earlier save. The env takes the run's own ``env_kwargs`` (its episode length,
    for one), which may differ from today's YAML entry.

    :param run: the zoo run folder (``logs/<algo>/<env>_<n>``)
    :param algo: the zoo name of the run's algorithm
    :param env_id: the run's env
    :param seed: the seed of the evaluation env
    :param n_envs: the evaluation env's number of envs
    :param model_file: the model to load instead of the run's final model
    :return: ``(model, env)``
    """
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
