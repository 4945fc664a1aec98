"""The scripts' shared helpers: the run-configuration loader of the package, and how the scripts evaluate and measure.

The loader (reading ``hyperparams/<algo>.yml`` and a run's ``config.yml``, building models and envs as the zoo does)
lives in :mod:`sb3_dipper.zoo.run_config`; its names are re-exported here for the scripts and for code that imports
them from ``zoo_scripts.configs``.
"""

from __future__ import annotations

import argparse
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecEnv

from sb3_dipper.common.files import write_bytes_atomically
from sb3_dipper.common.hierarchical import HierarchicalAlgorithm
from sb3_dipper.dipper import DIPPER
from sb3_dipper.raps import RAPS
from sb3_dipper.zoo.run_config import (
    ALGORITHMS,
    EVALUATED_KEYS,
    HYPERPARAMS_DIR,
    NAMESPACE,
    ZOO_KEYS,
    checkpoints,
    load_entry,
    make_env,
    make_model,
    run_env_kwargs,
    trained_run,
)

__all__ = [
    "ALGORITHMS",
    "EVALUATED_KEYS",
    "HYPERPARAMS_DIR",
    "NAMESPACE",
    "ZOO_KEYS",
    "checkpoints",
    "collected_dipper",
    "episode_successes",
    "evaluate",
    "goal_and_way",
    "load_entry",
    "make_env",
    "make_model",
    "measure_runs",
    "pair_measurement_parser",
    "parsed_pair_arguments",
    "run_env_kwargs",
    "torch_threads",
    "trained_run",
]


# The research tools measure trained models on episodes from this seed on, which no demonstration saw (the
# demonstrations are the episodes from seed 0 on); every case of a tool starts from the same episodes.
UNSEEN_EPISODES_SEED = 20_000


def trained_hierarchy(
    run: Path, algo: str, env_id: str, model_file: Path | None = None
) -> tuple[HierarchicalAlgorithm, VecEnv]:
    """:func:`trained_run` on unseen episodes (:data:`UNSEEN_EPISODES_SEED`), refused with the reason unless the model's
    higher level proposes subgoals to a learned lower level (RAPS's lower level is scripted; flat models have none)."""
    model, env = trained_run(run, algo, env_id, seed=UNSEEN_EPISODES_SEED, model_file=model_file)
    if not isinstance(model, HierarchicalAlgorithm) or isinstance(model, RAPS) or model.subgoal_space is None:
        raise ValueError(
            f"{run}: the model is a {type(model).__name__}, not a hierarchical model with a learned lower level "
            "(--algo names a DIPPER, HIER, PIPER, SAGA or HAC entry)"
        )
    return model, env


def collected_dipper(
    run: Path, algo: str, env_id: str, n_steps: int, model_file: Path | None = None, seed: int = UNSEEN_EPISODES_SEED
) -> tuple[DIPPER, int]:
    """The DIPPER of ``run`` (or ``model_file``) after ``n_steps`` primitive steps collected as training collects them
    (its exploration and goal episodes included) without an update, so that its trajectory buffer holds what a
    training round would draw pairs from, and the primitive steps it had trained; refused with the reason unless the
    model is a DIPPER."""
    model, _ = trained_run(run, algo, env_id, seed=seed, model_file=model_file)
    if not isinstance(model, DIPPER):
        raise ValueError(f"{run}: the model is a {type(model).__name__}, not a DIPPER (--algo names a DIPPER entry)")
    trained_steps = model.num_timesteps
    model.train = lambda *args, **kwargs: None  # type: ignore[method-assign]  # collect only
    model.learn(n_steps, reset_num_timesteps=False)
    return model, trained_steps


def goal_and_way(model: HierarchicalAlgorithm, observation: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The goal of ``observation`` as a subgoal and the unit way still to go, from the achieved goal to that goal (zero
    where they coincide), in world units, ``(..., subgoal_dim)`` each for observations ``(..., goal_dim)``."""
    assert model.subgoal_space is not None
    space = model.subgoal_space
    goals = space.to_world(model._subgoal_actions(observation["desired_goal"]))
    way = goals - space.to_world(model._subgoal_actions(observation["achieved_goal"], "achieved_goal"))
    return goals, way / np.maximum(np.linalg.norm(way, axis=-1, keepdims=True), 1e-8)


def pair_measurement_parser(description: str) -> argparse.ArgumentParser:
    """:func:`measurement_parser` for the tools that measure pairs drawn from what a DIPPER collects
    (:func:`collected_dipper`): ``--steps`` collected and ``--pairs`` drawn per model, no ``--episodes``."""
    parser = measurement_parser(description, episodes=None, algo_help="a DIPPER entry")
    parser.add_argument("--steps", type=int, default=6000, help="primitive steps collected per model")
    parser.add_argument("--pairs", type=int, default=4000, help="pairs drawn from what was collected")
    return parser


def parsed_pair_arguments(parser: argparse.ArgumentParser) -> argparse.Namespace:
    """The arguments of a :func:`pair_measurement_parser`, ``--steps`` and ``--pairs`` checked."""
    args = parser.parse_args()
    if args.steps < 1 or args.pairs < 1:
        parser.error("--steps and --pairs must be at least 1")
    args.episodes = 0  # measure_runs passes it on; these tools count steps and pairs instead
    return args


# measure(run, algo, env_id, steps, pairs, model_file) -> (the model's primitive steps, its results per case)
PairMeasure = Callable[[Path, str, str, int, int, "Path | None"], tuple[int, dict[str, dict[str, float]]]]


def measure_pair_runs(description: str, measure: PairMeasure, report: str, columns: tuple[str, ...]) -> None:
    """The command line of a tool that measures pairs drawn from what a DIPPER collects: :func:`parsed_pair_arguments`
    of a :func:`pair_measurement_parser`, one torch thread, and :func:`measure_runs` with
    ``measure(run, algo, env_id, steps, pairs, model_file)``."""
    parser = pair_measurement_parser(description)
    args = parsed_pair_arguments(parser)
    th.set_num_threads(1)

    def measure_model(run: Path, algo: str, env_id: str, _: int, model_file: Path | None) -> tuple[int, dict]:
        return measure(run, algo, env_id, args.steps, args.pairs, model_file)

    measure_runs(parser, args, measure_model, report, columns)


def measurement_parser(
    description: str, episodes: int | None, algo: str | None = "dipper", algo_help: str = "a hierarchical entry"
) -> argparse.ArgumentParser:
    """The command line every tool of :func:`measure_runs` shares: the zoo run folders, ``--algo``, ``--env``,
    ``--episodes`` (with its default; none where ``episodes`` is ``None``), ``--csv`` and ``--checkpoints``.

    :param description: the tool's docstring, shown by ``--help``
    :param algo: the zoo name ``--algo`` defaults to (``None``: it must be given)
    :param algo_help: what ``--algo`` names, in the help
    """
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", type=Path, nargs="+", help="zoo run folders (logs/<algo>/<env>_<n>) holding <env>.zip")
    parser.add_argument("--algo", default=algo, required=algo is None, help=f"zoo name of the models' algorithm ({algo_help})")
    parser.add_argument("--env", help="task (default: each run folder's name without its _<n>)")
    if episodes is not None:
        parser.add_argument("--episodes", type=int, default=episodes)
    parser.add_argument("--csv", type=Path, help="also write every model's results to this CSV")
    parser.add_argument("--checkpoints", action="store_true", help="also measure every rl_model_<steps>_steps.zip of a run")
    return parser


def measure_runs(
    parser: argparse.ArgumentParser,
    args: argparse.Namespace,
    measure: Callable[[Path, str, str, int, Path | None], tuple[int, dict[str, dict[str, float]]]],
    report: str,
    columns: tuple[str, ...],
) -> None:
    """Measure every run of ``args.runs`` with ``measure(run, args.algo, env_id, args.episodes, model_file)``
    (``model_file`` ``None``: the run's final model, where it has one), also at every checkpoint the run kept with
    ``args.checkpoints``; print each result, write the final model's as ``<run>/<report>`` (JSON) and, with
    ``args.csv``, one CSV row per model and case.

    :param columns: the CSV's case column and its metrics, e.g. ``("driver", "success", "options_reached")``
    """
    case_column, *metrics = columns
    rows = [",".join(("run", "steps", case_column, *metrics))]
    missing = [str(run) for run in args.runs if not run.is_dir()]
    if missing:
        parser.error(f"{', '.join(missing)}: no such run folder (a zoo run folder, e.g. logs/dipper/<env>_1)")
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


def evaluate(
    model: HierarchicalAlgorithm,
    env: VecEnv,
    n_episodes: int,
    goal_as_subgoal: bool = False,
    sample_higher: bool = False,
    sample_lower: bool = False,
) -> dict[str, float]:
    """Success over ``n_episodes``, the share of higher-level decisions the planner made, and how far the subgoals
    decided lie from the goal and from where the agent was when deciding (``subgoal_to_goal``,
    ``subgoal_to_achieved``: mean distances in the subgoal space, world units); both levels act deterministically unless
    told to sample.

    :param goal_as_subgoal: replace the higher level by the env's goal as every subgoal (the lower level alone)
    :param sample_higher: the higher level samples its policy, as while collecting
    :param sample_lower: the lower level samples its policy, as while collecting
    """
    decisions = {"planned": 0, "all": 0}
    distances: dict[str, list[float]] = {"subgoal_to_goal": [], "subgoal_to_achieved": []}
    decide = model._high_level_actions

    def counted(observation, deterministic):  # type: ignore[no-untyped-def]  # the case decides, not predict's flag
        if goal_as_subgoal:
            actions = model._subgoal_actions(observation["desired_goal"])
        else:
            actions = decide(observation, not sample_higher)
            planned = model.last_planned if isinstance(model, DIPPER) else np.zeros(len(actions), dtype=bool)
            decisions["planned"] += int(planned.sum())
            decisions["all"] += int(planned.size)
        subgoals = model.subgoal_space.to_world(actions)
        for key, goal_key in (("subgoal_to_goal", "desired_goal"), ("subgoal_to_achieved", "achieved_goal")):
            targets = model.subgoal_space.to_world(model._subgoal_actions(observation[goal_key], goal_key))
            distances[key].extend(model.subgoal_space.distance(subgoals, targets).tolist())
        return actions

    model._high_level_actions = counted  # type: ignore[method-assign]
    try:
        success = float(np.mean(episode_successes(model, env, n_episodes, deterministic=not sample_lower)))
    finally:
        del model._high_level_actions
    return {
        "success": success,
        "planned_share": decisions["planned"] / max(decisions["all"], 1),
        **{key: float(np.mean(values)) if values else float("nan") for key, values in distances.items()},
    }


def torch_threads() -> int:
    """One torch thread per run unless ``SB3_DIPPER_THREADS`` says otherwise (runs are small; processes parallelise)."""
    return int(os.environ.get("SB3_DIPPER_THREADS", "1"))
