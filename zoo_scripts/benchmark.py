"""Benchmarks: throughput ratios and learning curves; BENCHMARKS.md sections (command, machine, date) only on request.

    python zoo_scripts/benchmark.py throughput                      # DIPPER/HIER seconds per step vs SB3 SAC+HER
    python zoo_scripts/benchmark.py profiles --write                # steps/s at the paper tasks' CPU profiles
    python zoo_scripts/benchmark.py profiles --envs FetchPushFixed-v0 --fused-adam   # and with fused Adam optimizers
    python zoo_scripts/benchmark.py profiles --envs FetchPush-v4 --variant b128 batch_size=128   # and a cheaper copy
    python zoo_scripts/benchmark.py updates                         # ms per lower/higher update vs SB3's SAC update
    python zoo_scripts/benchmark.py learning --algos dipper hier sac --seeds 0 1 2 --workers 2
    python zoo_scripts/benchmark.py learning --algos dipper --variant no-nll --set nll_coef=0.0 --name ablations
    python zoo_scripts/benchmark.py learning --protocol quick --out runs/quick            # every algorithm, <= 1 h
    python zoo_scripts/benchmark.py learning --protocol quick --out runs/quick --report-only --write   # BENCHMARKS.md
    python zoo_scripts/benchmark.py learning --protocol paper --ray-address HEAD:6379     # paper tasks on a cluster
    python zoo_scripts/benchmark.py learning --envs FetchPush-v4 FetchPickAndPlace-v4 --algos dipper sac --seeds 0 1

``learning`` runs every (algorithm, task, seed) triple as the RL-Zoo run a user would start::

    sb3-dipper-zoo train --algo ALGO --env ENV --seed SEED -f OUT/VARIANT/seed_SEED --eval-freq F --eval-episodes N \
        --n-eval-envs E --num-threads 1 [-n BUDGET] [--save-freq S] [--env-kwargs k:v ...] [-params k:v ...]

so hyperparameters come from the task's entry of ``hyperparams/<algo>.yml`` (``callback`` included) exactly as there,
``--set key=value`` and ``--env-kwargs key=value`` become the zoo's ``-params key:value`` and ``--env-kwargs key:value``
(the value is read as Python by rl-zoo3: quote strings, ``--set "value_reg='score'"``; the env kwargs apply to the
training and the evaluation envs), and each run is an ordinary zoo run folder::

    OUT/<variant or default>/seed_<n>/<algo>/<env>_1/
        0.monitor.csv ...         monitor files (episode return, length, is_success)
        <env>/config.yml args.yml command.txt
        <env>.zip best_model.zip  the final model; the best one by evaluation reward
        rl_model_<steps>_steps.zip  with --save-freq: the model every that many primitive steps
        evaluations.npz           SB3's EvalCallback: timesteps, results, ep_lengths, successes
        progress.csv              SB3's CSV log, where the YAML entry names CSVProgressCallback (the hierarchical
                                  algorithms): rollout/subgoal_distance, rollout/low_value, eval/success_rate, ...
        result.json               written by this script once the run trained its whole budget
    OUT/<variant or default>/seed_<n>/<algo>/<env>.log     the zoo's output of the run's last attempt

A run with ``result.json`` is skipped, so rerunning the same command after a crash redoes only the unfinished runs (their
leftover folders are removed first). Runs longer than a session are trained in parts: with ``--pause-after-minutes M``
each run pauses after M minutes of training with a resume checkpoint in its folder (``resume/``, see
``sb3-dipper-zoo train --pause-after-minutes``), and rerunning the command continues every paused run where it stopped,
in the same folder and on the same evaluation grid (``parts.json`` adds up the parts' time for ``result.json``).
``zoo_scripts/plot.py -f OUT/default/seed_*`` plots the runs like any zoo runs.
The report reads the runs on disk through ``plot.py``'s loaders (finished or not, ``--report-only`` without running
anything): a table per task (seeds, with the unfinished ones counted as partial, the last evaluation every seed has
reached, the success there as mean +- std over seeds, the steps where the mean success first reaches 50 %, and for
hierarchical algorithms the subgoal distance and lower value last logged at or before that step, for the
preference-trained ones the labelled pairs in their dataset then: what a person would have labelled), the CSV
``OUT/<name>.csv`` with one row per seed and evaluation, and a figure with a panel per task (``plot.draw_success``).
The tables are printed and the figure written to ``OUT/<name>.png``; only ``--write`` puts the section ``<name>`` into
BENCHMARKS.md (``--benchmarks-md``) and the figure and the CSV into docs/benchmarks/ (``--figures-dir``). Run folders
do not outlive the machine they ran on; the CSV does: with ``--previous-csv docs/benchmarks/<name>.csv`` a later report
takes every run it lists that has no folder in ``--out`` from it (its ``finished`` column keeps partial runs partial),
so a table grows across machines and sessions (the CSV's steps, success and metrics are the table's). rl-zoo3
evaluates every ``--eval-freq`` steps, so a budget that is not a multiple of it ends with its last evaluation up to
``--eval-freq`` steps before the end.

Runs execute locally, ``--workers`` zoo processes at a time, or with ``--ray-address`` as Ray tasks of one CPU each on a
running cluster (``ray start --head`` on one machine, ``ray start --address HEAD:6379`` on the others), each starting
the zoo process on its node. The Ray workers import this checkout and write into ``--out`` themselves, so every node
must see the checkout, its virtualenv and ``--out`` at the same paths (a shared filesystem) and run ``ray`` from that
virtualenv (``pip install -e ".[cluster]"``). Every run uses one torch thread (``SB3_DIPPER_THREADS`` to change it).

Protocols preset algorithms, tasks, seeds and budgets; flags given explicitly override them:

* ``quick``: ``PointMazeFourRooms-v0``, every algorithm but TQC, seeds 0 1 2, 40,000 primitive steps per run,
  evaluations of 20 episodes every 8,000 steps: under an hour on two cores. Measured here (the PointMaze entries, one
  torch thread, 2,400 steps after ``learning_starts``, while another two-process benchmark shared the two cores), in
  ms per primitive step: dipper 4.8, dipper_paper 3.3, dipper_nov 3.2, hier 3.4, hac 5.8, raps 0.9, piper 3.8, saga
  5.1, dac 17.5, dpo_flat 10.5, sac 5.5 (sum 63.6); a 20-episode evaluation took 2.6-9.8 s (sum 52 s). Alone on a
  core a run is faster: DIPPER's 2e5-step runs took 2.4 ms per step against 4.8 measured, so take 0.6 of the
  measurement. 3 seeds x (63.6 ms x 40,000 + 5 x 52 s) x 0.6 / 2 workers = 2,520 s = 42 min, plus at most one DAC
  run (40,000 x 17.5 ms x 0.6 = 7 min) left alone at the end: under 50 minutes.
* ``cpu``: the paper's tasks (the authors' fixed variants first) at the CPU profiles of ``hyperparams/<algo>.yml``
  and their budgets (150k steps on pick-and-place, 640k on push, 675k on the kitchen, 700k on the maze), DIPPER, the
  paper's DIPPER, DIPPER-No-V, HIER, PIPER, DAC and SAC+HER, seeds 0-2, 20 evaluation episodes every 15,000 steps.
  Narrow it with ``--envs``, ``--algos`` and ``--seeds``; measured run times are in BENCHMARKS.md.
* ``paper``: the paper's four tasks, the paper's algorithms (and this package's DIPPER), seeds 0-4, the YAML budgets
  (6.3e5 to 1.35e6 primitive steps with 3x512 networks and batches of 1024, not timed here: 220 runs for a big
  machine or a Ray cluster), evaluations of 50 episodes every 25,000 steps.
"""

from __future__ import annotations

import argparse
import ast
import csv
import datetime
import inspect
import json
import os
import platform
import random
import shlex
import shutil
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import torch as th

sys.path.insert(0, str(Path(__file__).resolve().parent))
import plot
from configs import ALGORITHMS, ZOO_KEYS, load_entry, make_env, make_model, torch_threads
from plot import LABELS, label

from sb3_dipper.common.files import write_bytes_atomically
from sb3_dipper.zoo import RESUME_FOLDER, RESUME_MODEL, saved_steps

REPO = Path(__file__).resolve().parent.parent
BENCHMARKS_MD = REPO / "BENCHMARKS.md"
RESULTS_DIR = REPO / "docs" / "benchmarks"
POINT_MAZE = "PointMazeFourRooms-v0"
PAPER_TASKS = ["FetchFourRoomMaze-v0", "FetchPickAndPlace-v4", "FetchPush-v4", "FrankaKitchenMicrowaveBurner-v0"]
# The paper's tasks with the authors' fixed variants first: the CPU profiles of hyperparams/<algo>.yml, one core per run.
CPU_TASKS = [
    "FetchPickAndPlaceFixed-v0",
    "FetchPushFixed-v0",
    "FrankaKitchenMicrowaveBurner-v0",
    "FetchPickAndPlace-v4",
    "FetchPush-v4",
    "FetchFourRoomMazeFixed-v0",
    "FetchFourRoomMaze-v0",
]
# The paper's comparison (its DIPPER, DIPPER-No-V and baselines, SAC+HER as FLAT) plus this package's DIPPER.
PAPER_ALGORITHMS = ["dipper", "dipper_paper", "dipper_nov", "hier", "hac", "raps", "piper", "saga", "dac", "dpo_flat", "sac"]
LEARNING_DEFAULTS: dict[str, Any] = dict(
    envs=[POINT_MAZE], algos=["dipper", "hier", "sac"], seeds=[0, 1, 2], n_timesteps=None, eval_freq=20_000, eval_episodes=50
)
PROTOCOLS: dict[str, dict[str, Any]] = {
    "quick": dict(
        envs=[POINT_MAZE],
        algos=PAPER_ALGORITHMS,
        seeds=[0, 1, 2],
        n_timesteps=40_000,
        eval_freq=8_000,
        eval_episodes=20,
    ),
    "paper": dict(envs=PAPER_TASKS, algos=PAPER_ALGORITHMS, seeds=[0, 1, 2, 3, 4], n_timesteps=None, eval_freq=25_000),
    "cpu": dict(
        envs=CPU_TASKS,
        algos=["dipper", "dipper_paper", "dipper_nov", "hier", "piper", "dac", "sac"],
        seeds=[0, 1, 2],
        n_timesteps=None,
        eval_freq=15_000,
        eval_episodes=20,
    ),
}
# Logged by the option layer of hierarchical algorithms (``rollout/<key>`` in progress.csv); read at each evaluation.
OPTION_METRICS = ("subgoal_distance", "low_value")
# The labelled pairs in the preference dataset (DIPPER, PIPER: ``train/high_preference_pairs``): what a person would
# have labelled to get the result, had a person given the labels.
PREFERENCE_PAIRS = "preference_pairs"
PREFERENCE_PAIRS_KEY = "train/high_preference_pairs"
# The training episodes' success over the last 100 episodes, from the monitor files: the authors' "train success rate".
TRAINING_SUCCESS = "train_success"
CSV_METRICS = (*OPTION_METRICS, TRAINING_SUCCESS, PREFERENCE_PAIRS)
# The report's CSV: a row per run and evaluation; ``finished`` is 1 once the run had trained its whole budget.
CSV_COLUMNS = ("env", "algo", "seed", "timesteps", "success", *CSV_METRICS, "finished")


# ------------------------------------------------------------------------------------------------------------- report


def machine() -> str:
    return f"{os.cpu_count()} cores, {platform.processor() or platform.machine()}, torch {th.__version__}, no GPU"


def command_line(script: str, arguments: list[str]) -> str:
    """The shell command that runs ``zoo_scripts/<script>`` with ``arguments``, each quoted where a shell would split or
    read it (``--set "value_reg='score'"``), so a stamped command reruns as it ran."""
    return shlex.join(["python", f"zoo_scripts/{script}", *arguments])


def write_section(name: str, body: str, command: str, path: Path = BENCHMARKS_MD) -> None:
    """Replace (or append) the ``name`` section of ``path`` (BENCHMARKS.md), stamped with command, machine and date."""
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    stamp = f"Command: `{command}`  \nMachine: {machine()}  \nDate: {datetime.date.today().isoformat()}\n\n"
    section = f"{start}\n{stamp}{body.strip()}\n{end}"
    text = path.read_text() if path.exists() else "# Benchmarks\n"
    if start in text and end in text:
        text = text[: text.index(start)] + section + text[text.index(end) + len(end) :]
    else:
        text = f"{text.rstrip()}\n\n{section}\n"
    write_bytes_atomically(path, text.encode())


# ------------------------------------------------------------------------------------------------------------- throughput

THROUGHPUT_LOWER = dict(batch_size=256, buffer_size=100_000, learning_starts=1000, gamma=0.95, tau=0.005)


def throughput_models(env_id: str, net_arch: list[int]) -> dict[str, Any]:
    """SAC+HER and the hierarchical algorithms with the same lower networks, batch size and updates per step."""
    models = {}
    for algo in ("sac", "hier", "dipper", "dipper_paper"):
        overrides: dict[str, Any] = dict(THROUGHPUT_LOWER, n_envs=1)
        if algo == "sac":
            overrides.update(policy_kwargs=dict(net_arch=net_arch), train_freq=1, gradient_steps=1)
        else:
            overrides.update(low_policy_kwargs=dict(net_arch=net_arch), train_freq=1, gradient_steps=1)
        models[algo] = make_model(algo, env_id, seed=0, overrides=overrides)[0]
    return models


def interleaved_seconds(chunks: Mapping[str, Callable[[], Any]], repeats: int) -> dict[str, list[float]]:
    """Seconds of each of ``repeats`` calls of every chunk of work, the chunks in a new random order every round, so
    that every one meets the machine's changing load alike."""
    seconds: dict[str, list[float]] = {name: [] for name in chunks}
    order = list(chunks)
    for _ in range(repeats):
        random.shuffle(order)
        for name in order:
            start = time.perf_counter()
            chunks[name]()
            seconds[name].append(time.perf_counter() - start)
    return seconds


def training_chunks(models: dict[str, Any], steps: int) -> dict[str, Callable[[], Any]]:
    """``steps`` more training steps of each model, as chunks for :func:`interleaved_seconds`."""
    return {name: partial(model.learn, steps, reset_num_timesteps=False) for name, model in models.items()}


def run_throughput(args: argparse.Namespace) -> None:
    th.set_num_threads(torch_threads())
    models = throughput_models(args.env, args.net_arch)
    for model in models.values():
        model.learn(THROUGHPUT_LOWER["learning_starts"] + args.steps)
    seconds = interleaved_seconds(training_chunks(models, args.steps), args.repeats)
    seconds = {algo: [chunk / args.steps for chunk in chunks] for algo, chunks in seconds.items()}
    per_step = {algo: statistics.median(values) for algo, values in seconds.items()}
    write_bytes_atomically(
        RESULTS_DIR / "throughput.json", json.dumps({"seconds_per_step": seconds, "median": per_step}, indent=1).encode()
    )
    rows = [f"| {LABELS[algo]} | {per_step[algo] * 1e3:.2f} | {per_step[algo] / per_step['sac']:.2f} |" for algo in models]
    body = (
        f"Seconds per primitive step on `{args.env}`, one env, lower networks {args.net_arch}, batch 256, one lower "
        f"gradient step per primitive step for every algorithm (SAC+HER: its only level). Median of {args.repeats} "
        f"interleaved chunks of {args.steps} steps after warm-up, measured in one process.\n\n"
        "| algorithm | ms per step | ratio to SAC+HER |\n|---|---|---|\n" + "\n".join(rows)
    )
    write_section("throughput", body, command_line("benchmark.py", sys.argv[1:]))
    print(body)


def env_steps_per_second(env_id: str, n_envs: int, steps: int) -> float:
    """Primitive steps per second of the task's vectorised env under uniformly random actions (the limit if updates
    and acting were free)."""
    env = make_env(env_id, {"n_envs": n_envs}, seed=0)
    env.reset()
    start = time.perf_counter()
    for _ in range(steps // n_envs):
        env.step(np.stack([env.action_space.sample() for _ in range(n_envs)]))
    seconds = time.perf_counter() - start
    env.close()
    return (steps // n_envs) * n_envs / seconds


FUSED_ADAM = "fused"  # the variant name of a profile whose optimizers are fused Adam


def fused_adam_overrides(algo: str, env_id: str) -> dict[str, Any]:
    """The entry's network kwargs of every level with ``optimizer_kwargs={"fused": True}``: ``torch.optim.Adam``'s
    one-kernel update of all parameters instead of its loop over tensors in Python, the same math (the SAC entropy
    coefficient's own optimizer, used only with ``ent_coef='auto'``, stays SB3's)."""
    entry = load_entry(algo, env_id)
    levels = ["policy_kwargs"]
    if "low_policy_kwargs" in inspect.signature(ALGORITHMS[algo]).parameters:
        levels.append("low_policy_kwargs")
    overrides = {}
    for key in levels:
        kwargs = dict(entry.get(key) or {})
        kwargs["optimizer_kwargs"] = {**kwargs.get("optimizer_kwargs", {}), "fused": True}
        overrides[key] = kwargs
    return overrides


def profile_variants(variants: list[list[str]]) -> dict[str, dict[str, Any]]:
    """``--variant NAME KEY=VALUE ...`` of ``profiles`` as ``{NAME: {KEY: value}}``, the values Python literals.

    :param variants: one list per ``--variant``: its name, then its assignments
    """
    parsed: dict[str, dict[str, Any]] = {}
    for name, *assignments in variants:
        if "=" in name or not assignments:
            raise ValueError(f"--variant takes a name, then key=value (e.g. --variant b128 batch_size=128), got {name!r}")
        overrides = {}
        for assignment in assignments:
            key, separator, value = assignment.partition("=")
            if not separator or not key:
                raise ValueError(f"--variant {name} takes key=value after its name, got {assignment!r}")
            try:
                overrides[key] = ast.literal_eval(value)
            except (ValueError, SyntaxError):
                raise ValueError(
                    f"--variant {name} {assignment}: {value!r} is not a Python literal "
                    "(a number, string in quotes, list or dict: policy_kwargs=\"{'net_arch': [64, 64]}\")"
                ) from None
        parsed[name] = overrides
    return parsed


def variant_overrides(algo: str, env_id: str, changes: dict[str, Any]) -> dict[str, Any] | None:
    """One ``--variant``'s ``changes`` as overrides of an algorithm's entry, or None where the algorithm lacks a keyword.

    A dict value updates the entry's dict (``policy_kwargs={'optimizer_kwargs': {'fused': True}}`` keeps the entry's
    ``net_arch``), so a variant changes only what it names; a variant of a lower level's keywords
    (``low_policy_kwargs``, ``bc_coef``) is skipped for SAC+HER, which has none.
    """
    # Deprecated keywords too (bc_coef: demo_kwargs["bc_coef"]), which the constructors still take.
    keywords = set(inspect.signature(ALGORITHMS[algo]).parameters) | set(ZOO_KEYS)
    keywords |= set(getattr(ALGORITHMS[algo], "deprecated_parameters", {}))
    if not set(changes) <= keywords:
        return None
    entry = load_entry(algo, env_id)
    return {
        key: {**entry[key], **value} if isinstance(value, dict) and isinstance(entry.get(key), dict) else value
        for key, value in changes.items()
    }


def run_profiles(args: argparse.Namespace) -> None:
    """Training steps per second of each algorithm at each task's CPU profile, beside the env's own step rate.

    The models of one task are warmed up past ``learning_starts``, then trained in interleaved chunks of
    ``--steps`` primitive steps (the median chunk counts), in this one process, so the ratios share the machine's state.
    With ``--fused-adam`` each algorithm is measured a second time, as ``<algo>-fused``, with fused Adam optimizers;
    each ``--variant NAME KEY=VALUE ...`` measures it once more, as ``<algo>-NAME``, with those hyperparameters changed
    (:func:`variant_overrides`).
    """
    th.set_num_threads(torch_threads())
    variants = profile_variants(args.variant)
    rows, records = [], []
    for env_id in args.envs:
        models = {algo: make_model(algo, env_id, seed=0)[0] for algo in args.algos}
        if args.fused_adam:
            for algo in args.algos:
                overrides = fused_adam_overrides(algo, env_id)
                models[f"{algo}-{FUSED_ADAM}"] = make_model(algo, env_id, seed=0, overrides=overrides)[0]
        for name, changes in variants.items():
            for algo in args.algos:
                variant = variant_overrides(algo, env_id, changes)
                if variant is not None:
                    models[f"{algo}-{name}"] = make_model(algo, env_id, seed=0, overrides=variant)[0]
            if not any(f"{algo}-{name}" in models for algo in args.algos):
                raise ValueError(f"--variant {name}: none of {', '.join(args.algos)} takes {', '.join(sorted(changes))}")
        n_envs = models[args.algos[0]].n_envs
        env_rate = env_steps_per_second(env_id, n_envs, args.steps)
        for model in models.values():
            model.learn(int(getattr(model, "learning_starts", 0)) + args.steps)
        seconds = interleaved_seconds(training_chunks(models, args.steps), args.repeats)
        rates = {algo: args.steps / statistics.median(values) for algo, values in seconds.items()}
        baseline = rates.get("sac")
        for algo, rate in rates.items():
            versus_sac = f"{rate / baseline:.2f}" if baseline else "-"
            ratios = f"{rate / env_rate:.2f} | {versus_sac}"
            rows.append(f"| `{env_id}` | {label(algo)} | {rate:.0f} | {env_rate:.0f} | {ratios} |")
            records.append(f"{env_id},{algo},{models[algo].n_envs},{rate:.2f},{env_rate:.2f}")
        print(rows[-len(rates) :], flush=True)
    csv = RESULTS_DIR / f"{args.name}.csv"
    body = (
        "Primitive steps per second while training, at each task's CPU profile (`hyperparams/<algo>.yml`), one torch "
        f"thread, median of {args.repeats} interleaved chunks of {args.steps:,} steps after `learning_starts`, measured "
        "in one process; the env rate is the same vectorised env under random actions (the limit if updates were "
        f"free). CSV: `{os.path.relpath(csv, REPO)}`.\n\n"
        "| task | algorithm | training steps/s | env steps/s | ratio to env | ratio to SAC+HER |\n|---|---|---|---|---|---|\n"
        + "\n".join(rows)
    )
    if args.write:
        header = "env,algo,n_envs,train_steps_per_second,env_steps_per_second"
        write_bytes_atomically(csv, "\n".join([header, *records, ""]).encode())
        write_section(args.name, body, command_line("benchmark.py", sys.argv[1:]))
    print(body)


# ------------------------------------------------------------------------------------------------------------- updates


def update_steps(model: Any) -> dict[str, Any]:
    """One update of each kind on a trained DIPPER: SB3's own ``SAC.train`` on the lower SAC (same networks, buffer and
    batch), the lower level's DemoSAC step (behaviour cloning, clipped targets) and DIPPER's higher-level update."""
    from stable_baselines3 import SAC

    lower, batch_size = model.lower, model.batch_size
    return {
        "SB3 SAC.train, 1 gradient step": lambda: SAC.train(lower, 1, batch_size),
        "DemoSAC.train, 1 gradient step": lambda: lower.train(1, batch_size),
        "DIPPER higher-level update": model._train_high_level,
    }


def repeat_call(function: Callable[[], Any], times: int) -> None:
    for _ in range(times):
        function()


def run_updates(args: argparse.Namespace) -> None:
    """Milliseconds per training update at a task's DIPPER CPU profile, and their ratios to SB3's SAC update.

    The model trains ``learning_starts + --warmup`` primitive steps first (filled buffers, labelled pairs); then each
    kind of update runs ``--updates`` times per round, the kinds in a new random order every round, all in this one
    process, so the ratios share the machine's state (the absolute times do not travel).
    """
    th.set_num_threads(torch_threads())
    model = make_model("dipper", args.env, seed=0)[0]
    model.learn(int(getattr(model, "learning_starts", 0)) + args.warmup)
    chunks = {name: partial(repeat_call, update, args.updates) for name, update in update_steps(model).items()}
    seconds = interleaved_seconds(chunks, args.repeats)
    per_update = {name: statistics.median(values) / args.updates for name, values in seconds.items()}
    baseline = per_update["SB3 SAC.train, 1 gradient step"]
    rows = [f"| {name} | {value * 1e3:.2f} | {value / baseline:.2f} |" for name, value in per_update.items()]
    print(
        f"Milliseconds per update at `{args.env}`'s DIPPER CPU profile (`hyperparams/dipper.yml`), one torch thread, "
        f"median of {args.repeats} interleaved rounds of {args.updates} updates after {args.warmup:,} training steps "
        "past `learning_starts`, measured in one process.\n\n"
        "| update | ms per update | ratio to SB3 SAC |\n|---|---|---|\n" + "\n".join(rows)
    )


# ------------------------------------------------------------------------------------------------------------- learning


DEFAULT_VARIANT = "default"  # the folder of the runs without --variant
RESULT = "result.json"
PARTS = "parts.json"  # the training time of a paused run's parts


def run_name(algo: str, variant: str | None) -> str:
    """The name of an algorithm's runs in tables, figure and CSV: ``<algo>`` or ``<algo>-<variant>``."""
    return algo if variant is None else f"{algo}-{variant}"


def seed_folder(out: Path, variant: str | None, seed: int) -> Path:
    """The zoo log folder (``train -f``) of one seed of a variant: ``<out>/<variant or 'default'>/seed_<seed>``."""
    return out / (variant or DEFAULT_VARIANT) / f"seed_{seed}"


def zoo_pairs(flag: str, assignments: list[str]) -> list[str]:
    """``key=value`` assignments as rl-zoo3's ``key:value`` (its ``-params`` and ``--env-kwargs``).

    rl-zoo3 evaluates each value as Python. A bare word such as ``value_reg=score`` would be a name it cannot evaluate
    (in every run, after its start-up), so it is refused here with the quoting that works.

    :param flag: the option the assignments came from, for the error message
    :param assignments: ``key=value`` strings
    """
    pairs = []
    for assignment in assignments:
        key, separator, value = assignment.partition("=")
        try:
            expression = ast.parse(value, mode="eval").body if separator and key else None
        except SyntaxError as error:
            raise ValueError(f"{flag} {assignment}: {value!r} is not a Python expression ({error.msg})") from None
        if expression is None:
            raise ValueError(f"{flag} takes key=value (e.g. {flag} learning_starts=1000), got {assignment!r}")
        if isinstance(expression, ast.Name):
            raise ValueError(
                f"{flag} {assignment}: rl-zoo3 reads the value as Python, where {value} is an undefined name; "
                f"quote a string: {flag} \"{key}='{value}'\""
            )
        pairs.append(f"{key}:{value}")
    return pairs


def zoo_flags(args: argparse.Namespace) -> list[str]:
    """The ``sb3-dipper-zoo train`` flags every run of this command shares (evaluation, budget, overrides)."""
    n_eval_envs = args.n_eval_envs or min(args.eval_episodes, 10)
    flags = ["--eval-freq", str(args.eval_freq), "--eval-episodes", str(args.eval_episodes), "--n-eval-envs", str(n_eval_envs)]
    if args.pause_after_minutes is not None:
        flags += ["--pause-after-minutes", str(args.pause_after_minutes)]
    if args.save_freq:
        flags += ["--save-freq", str(args.save_freq)]
    if args.n_timesteps:
        flags += ["-n", str(args.n_timesteps)]
    if args.env_kwargs:
        flags += ["--env-kwargs", *zoo_pairs("--env-kwargs", args.env_kwargs)]
    if args.set:
        flags += ["-params", *zoo_pairs("--set", args.set)]
    return flags


def finished(run: Path) -> bool:
    return (run / RESULT).exists()


def model_steps(run: Path) -> tuple[int, int] | None:
    """``num_timesteps`` and ``_total_timesteps`` of the run's final model, or None before it has one."""
    env_name = run.name.rsplit("_", 1)[0]  # the zoo names the run folder <env>_<n> and the model <env>.zip
    model = run / f"{env_name}.zip"
    return saved_steps(model) if model.exists() else None


def trained_to_the_end(run: Path) -> bool:
    """Whether the run's final model trained its whole budget: rl-zoo3 also saves the model of a run stopped by Ctrl-C
    or paused by ``--pause-after-minutes``."""
    steps = model_steps(run)
    return steps is not None and steps[0] >= steps[1]


def resumable(run: Path) -> bool:
    """Whether an unfinished run was paused with a resume checkpoint (``sb3-dipper-zoo train --pause-after-minutes``)."""
    return not finished(run) and (run / RESUME_FOLDER / RESUME_MODEL).is_file()


def add_part_seconds(run: Path, seconds: float) -> float:
    """Add a part's training time to the run's ``parts.json``; the run's time so far."""
    total = seconds + (float(json.loads((run / PARTS).read_text())["seconds"]) if (run / PARTS).exists() else 0.0)
    write_bytes_atomically(run / PARTS, json.dumps({"seconds": total}).encode())
    return total


def learning_run(algo: str, env_id: str, seed: int, out: Path, variant: str | None, flags: list[str]) -> str:
    """One run: ``sb3-dipper-zoo train`` in a process of its own, then ``result.json`` in its run folder.

    Folders an unfinished attempt left (a crash, a kill) are removed first, so the run folder is ``<env>_1`` again.

    :param flags: the zoo flags of :func:`zoo_flags`
    :return: a line for the console
    """
    log_folder = seed_folder(out, variant, seed)
    paused = [run for run in plot.zoo_runs(log_folder, algo, env_id) if resumable(run)]
    for unfinished in plot.zoo_runs(log_folder, algo, env_id):
        if not finished(unfinished) and unfinished not in paused[-1:]:
            shutil.rmtree(unfinished)
    output = log_folder / algo / f"{env_id}.log"
    output.parent.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "sb3_dipper.zoo", "train", "--algo", algo, "--env", env_id, "--seed", str(seed)]
    command += ["-f", str(log_folder), "--num-threads", str(torch_threads()), *flags]
    if paused:
        command += ["--resume", str(paused[-1])]
    start = time.time()
    with open(output, "a" if paused else "w") as log:
        returncode = subprocess.run(command, stdout=log, stderr=subprocess.STDOUT).returncode
    seconds = time.time() - start
    runs = plot.zoo_runs(log_folder, algo, env_id)
    if returncode == 0 and runs and resumable(runs[-1]) and not trained_to_the_end(runs[-1]):
        add_part_seconds(runs[-1], seconds)
        steps = model_steps(runs[-1])
        done = f"{steps[0]:,} of {steps[1]:,}" if steps else "some"
        return f"{run_name(algo, variant)} {env_id} seed {seed}: paused after {done} steps; the same command resumes it"
    if returncode != 0 or not runs or not trained_to_the_end(runs[-1]):
        tail = "".join(output.read_text().splitlines(keepends=True)[-20:])
        raise RuntimeError(
            f"{run_name(algo, variant)} on {env_id}, seed {seed}: sb3-dipper-zoo train exited with {returncode} without "
            f"training its whole budget; its output is in {output}, ending with:\n{tail}"
        )
    seconds = add_part_seconds(runs[-1], seconds)  # a resumed run's time is the sum of its parts
    result = dict(algo=algo, variant=variant, env=env_id, seed=seed, seconds=seconds)
    write_bytes_atomically(runs[-1] / RESULT, json.dumps(result).encode())
    curve = plot.evaluation_curve(runs[-1])
    success = f", success {curve[1][-1]:.2f} at its last evaluation" if curve is not None else ""
    return f"{run_name(algo, variant)} {env_id} seed {seed}: {seconds / 60:.1f} min{success}"


@dataclass
class SeedCurve:
    """Every evaluation of one seed's run."""

    seed: int
    finished: bool  # the run has ended (result.json); a running or cut-off run is partial
    steps: np.ndarray  # (evaluations,) primitive steps
    success: np.ndarray  # (evaluations,) success rates
    metrics: dict[str, np.ndarray]  # every CSV_METRICS key, (evaluations,), NaN where not logged


@dataclass
class Curves:
    """The evaluations of one algorithm (or variant) on one task, at the evaluations every seed has reached (the
    table's mean), and each seed's own (the CSV, the figure's continuation of seeds that went further)."""

    steps: np.ndarray  # (evaluations,) primitive steps
    success: np.ndarray  # (seeds, evaluations) success rates
    metrics: dict[str, np.ndarray]  # every CSV_METRICS key, (seeds, evaluations), NaN where not logged
    per_seed: list[SeedCurve]

    @property
    def seeds(self) -> list[int]:
        return [seed_curve.seed for seed_curve in self.per_seed]

    @property
    def finished(self) -> list[bool]:
        return [seed_curve.finished for seed_curve in self.per_seed]


def run_seed_curve(run: Path, seed: int) -> SeedCurve | None:
    """The evaluations of one zoo run folder, read with plot.py's loaders, or None before its first evaluation.

    The option metrics at an evaluation are the last values ``progress.csv`` logged at or before its step.
    """
    curve = plot.evaluation_curve(run)
    if curve is None:
        return None
    log = plot.load_progress(run)
    logged: dict[str, plot.Curve | None] = {
        key: plot.metric_curve(log, f"rollout/{key}") if log is not None else None for key in OPTION_METRICS
    }
    logged[TRAINING_SUCCESS] = plot.training_success_curve(run)
    logged[PREFERENCE_PAIRS] = plot.metric_curve(log, PREFERENCE_PAIRS_KEY) if log is not None else None
    steps, success = curve
    metrics = {key: np.array([plot.value_at(logged[key], step) for step in steps]) for key in CSV_METRICS}
    return SeedCurve(seed=seed, finished=finished(run), steps=steps, success=success, metrics=metrics)


def read_report_csv(path: Path) -> dict[tuple[str, str, int], SeedCurve]:
    """The runs of a CSV that :func:`report` wrote, by ``(env, name, seed)``: runs whose folders are gone (a past
    session's machine, another machine) still count in a later report (``--previous-csv``).

    :raises ValueError: the file lacks a column :func:`report` writes (names the file and the columns)
    """
    with open(path, newline="") as file:
        reader = csv.DictReader(file)
        missing = [column for column in CSV_COLUMNS if column not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(
                f"{path} lacks the columns {missing} of a report CSV ({','.join(CSV_COLUMNS)}): pass a CSV that "
                "benchmark.py learning wrote"
            )
        rows: dict[tuple[str, str, int], list[dict[str, str]]] = {}
        for row in reader:
            rows.setdefault((row["env"], row["algo"], int(row["seed"])), []).append(row)
    return {
        (env_id, name, seed): SeedCurve(
            seed=seed,
            finished=all(row["finished"] == "1" for row in seed_rows),
            steps=np.array([float(row["timesteps"]) for row in seed_rows]),
            success=np.array([float(row["success"]) for row in seed_rows]),
            metrics={key: np.array([float(row[key] or "nan") for row in seed_rows]) for key in CSV_METRICS},
        )
        for (env_id, name, seed), seed_rows in rows.items()
    }


def load_curves(
    out: Path, name: str, env_id: str, seeds: list[int], previous: Mapping[tuple[str, str, int], SeedCurve]
) -> Curves | None:
    """The runs of ``name`` (``<algo>[-<variant>]``) on ``env_id`` that have evaluations: a seed with a run folder in
    ``out`` is read from its last one, any other from ``previous`` (:func:`read_report_csv`)."""
    algo, _, variant = name.partition("-")
    per_seed = []
    for seed in seeds:
        runs = plot.zoo_runs(seed_folder(out, variant or None, seed), algo, env_id)
        seed_curve = run_seed_curve(runs[-1], seed) if runs else previous.get((env_id, name, seed))
        if seed_curve is not None:
            per_seed.append(seed_curve)
    if not per_seed:
        return None
    steps, success = plot.align([(seed_curve.steps, seed_curve.success) for seed_curve in per_seed])
    metrics = {
        key: np.array([[plot.value_at((seed.steps, seed.metrics[key]), step) for step in steps] for seed in per_seed])
        for key in CSV_METRICS
    }
    return Curves(steps=steps, success=success, metrics=metrics, per_seed=per_seed)


def final_mean(curves: Curves, key: str, number_format: str = ".2f") -> str:
    """Mean over seeds of a metric at the last evaluation, or a dash where the algorithm does not log it; the number
    of seeds when only some of them have it."""
    final = curves.metrics[key][:, -1]
    if np.isnan(final).all():
        return "-"
    measured = int(np.count_nonzero(~np.isnan(final)))
    mean = format(np.nanmean(final), number_format)
    return mean + (f" ({measured} of {len(final)} seeds)" if measured < len(final) else "")


def task_table(
    out: Path, names: list[str], env_id: str, seeds: list[int], previous: Mapping[tuple[str, str, int], SeedCurve]
) -> tuple[str, dict[str, Curves], list[str]]:
    """Markdown table of one task (success at the last common evaluation, steps to 50 %, option metrics), its curves
    and its CSV rows."""
    curves: dict[str, Curves] = {}
    rows, csv_rows = [], []
    for name in names:
        run_curves = load_curves(out, name, env_id, seeds, previous)
        if run_curves is None:
            continue
        curves[name] = run_curves
        for seed_curve in run_curves.per_seed:
            for step_index, step in enumerate(seed_curve.steps):
                metrics = [seed_curve.metrics[key][step_index] for key in CSV_METRICS]
                values = ",".join("" if np.isnan(value) else f"{value:.4f}" for value in metrics)
                success = seed_curve.success[step_index]
                csv_rows.append(
                    f"{env_id},{name},{seed_curve.seed},{int(step)},{success:.4f},{values},{int(seed_curve.finished)}"
                )
        final = run_curves.success[:, -1]
        reached = np.flatnonzero(run_curves.success.mean(axis=0) >= 0.5)
        to_half = f"{int(run_curves.steps[reached[0]]):,}" if reached.size else "not reached"
        unfinished = run_curves.finished.count(False)
        runs = f"{len(run_curves.seeds)}" + (f" ({unfinished} partial)" if unfinished else "")
        rows.append(
            f"| {label(name)} | {runs} | {int(run_curves.steps[-1]):,} | {final.mean():.2f} +- {final.std():.2f} | "
            f"{final_mean(run_curves, TRAINING_SUCCESS)} | {to_half} | {final_mean(run_curves, 'subgoal_distance')} | "
            f"{final_mean(run_curves, 'low_value')} | {final_mean(run_curves, PREFERENCE_PAIRS, ',.0f')} |"
        )
    if not rows:
        return "No runs yet.", curves, csv_rows
    table = (
        "| algorithm | seeds | last evaluation (steps) | success there (mean +- std) | training success there (last 100 "
        "episodes) | steps to 50 % (mean curve) | subgoal distance there | lower value there | labelled pairs there |\n"
        "|---|---|---|---|---|---|---|---|---|\n"
    )
    return table + "\n".join(rows), curves, csv_rows


def report(
    out: Path,
    names: list[str],
    envs: list[str],
    seeds: list[int],
    name: str,
    figures_dir: Path,
    previous: Mapping[tuple[str, str, int], SeedCurve] | None = None,
) -> tuple[dict[str, str], dict[str, dict[str, Curves]], Path]:
    """Tables and curves per task, the CSV ``<out>/<name>.csv`` and the figure ``<figures_dir>/<name>.png``.

    :param names: the runs to report, ``<algo>`` or ``<algo>-<variant>``
    :param previous: runs without a folder in ``out``, from an earlier report's CSV (:func:`read_report_csv`)
    """
    tables, curves, csv_rows = {}, {}, [",".join(CSV_COLUMNS)]
    for env_id in envs:
        tables[env_id], curves[env_id], rows = task_table(out, names, env_id, seeds, previous or {})
        csv_rows += rows
    write_bytes_atomically(out / f"{name}.csv", ("\n".join(csv_rows) + "\n").encode())
    panels = {
        env_id: {run: [(seed.steps, seed.success) for seed in run_curves.per_seed] for run, run_curves in task.items()}
        for env_id, task in curves.items()
    }
    figure = plot.save(plot.draw_success(panels), figures_dir / name, ["png"])[0]
    return tables, curves, figure


def local_results(jobs: list[tuple[Any, ...]], workers: int) -> Iterator[str]:
    """The runs on this machine, ``workers`` zoo processes at a time; a failed run cancels the runs not yet started."""
    with ThreadPoolExecutor(max_workers=workers) as pool:
        futures = [pool.submit(learning_run, *job) for job in jobs]
        try:
            for future in as_completed(futures):
                yield future.result()
        finally:
            for future in futures:
                future.cancel()


def ray_results(jobs: list[tuple[Any, ...]], address: str) -> Iterator[str]:
    """The runs as Ray tasks of one CPU on the cluster at ``address``; they write into ``--out`` themselves."""
    import ray

    # Workers unpickle learning_run, which imports configs and plot from this directory: it must be on their path.
    python_path = [str(Path(__file__).resolve().parent), *filter(None, [os.environ.get("PYTHONPATH")])]
    env_vars = {"PYTHONPATH": os.pathsep.join(python_path), "MUJOCO_GL": os.environ["MUJOCO_GL"]}
    if "SB3_DIPPER_THREADS" in os.environ:
        env_vars["SB3_DIPPER_THREADS"] = os.environ["SB3_DIPPER_THREADS"]
    ray.init(address=address, runtime_env={"env_vars": env_vars})
    try:
        remote_run = ray.remote(num_cpus=1)(learning_run)
        pending = [remote_run.remote(*job) for job in jobs]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])
    finally:
        ray.shutdown()


def resolve_protocol(args: argparse.Namespace) -> None:
    """Fill the options not given on the command line from the protocol's presets, then from the defaults."""
    for key, value in {**LEARNING_DEFAULTS, **PROTOCOLS.get(args.protocol, {})}.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    args.name = args.name or args.protocol or "learning"


def run_learning(args: argparse.Namespace) -> tuple[dict[str, str], dict[str, dict[str, Curves]]]:
    resolve_protocol(args)
    # Absolute, so that Ray workers, whose working directory differs, write to the same place.
    out = Path(args.out).resolve()
    flags = zoo_flags(args)
    names = [run_name(algo, args.variant) for algo in args.algos]
    triples = [(algo, env_id, seed) for algo in args.algos for env_id in args.envs for seed in args.seeds]
    jobs = [
        (algo, env_id, seed, out, args.variant, flags)
        for algo, env_id, seed in triples
        if not any(finished(run) for run in plot.zoo_runs(seed_folder(out, args.variant, seed), algo, env_id))
    ]
    print(f"{len(jobs)} runs to do, {len(triples) - len(jobs)} already finished", flush=True)
    if not args.report_only:
        results = ray_results(jobs, args.ray_address) if args.ray_address else local_results(jobs, args.workers)
        for result in results:
            print(result, flush=True)
    figures_dir = Path(args.figures_dir or RESULTS_DIR) if args.write else out
    previous = read_report_csv(Path(args.previous_csv)) if args.previous_csv else None
    tables, curves, figure = report(out, args.report or names, args.envs, args.seeds, args.name, figures_dir, previous)
    budget = f"{args.n_timesteps:,} primitive steps per run" if args.n_timesteps else "the YAML budgets"
    overrides = " ".join(flags[flags.index("-params") + 1 :]) if args.set else ""
    description = (
        f"Seeds {args.seeds}, {budget}, deterministic success over {args.eval_episodes} episodes every "
        f"{args.eval_freq:,} primitive steps (rl-zoo3's EvalCallback); runs: `sb3-dipper-zoo train` with each task's "
        f"entry of `hyperparams/<algo>.yml`{f' and `-params {overrides}`' if overrides else ''}. Subgoal distance and "
        "lower value: as last logged to `progress.csv` at or before the last evaluation, the mean over the last 100 "
        "options (hierarchical algorithms). Training success: the stochastic policy's training episodes (monitor "
        "files), the last 100 finished by the last evaluation, as the authors' code logs its train success rate."
    )
    tables_text = "\n\n".join(f"`{env_id}`\n\n{table}" for env_id, table in tables.items())
    if args.write:
        markdown = Path(args.benchmarks_md or BENCHMARKS_MD)
        image = f"![success curves]({os.path.relpath(figure, markdown.resolve().parent)})"
        command = command_line("benchmark.py", sys.argv[1:])
        write_section(args.name, f"{description}\n\n{tables_text}\n\n{image}", command, markdown)
        # The CSV behind the table goes next to its figure, to be committed with it.
        shutil.copyfile(out / f"{args.name}.csv", figure.with_suffix(".csv"))
    print(f"{description}\n\n{tables_text}\n\nFigure: {figure}\nCSV: {out / f'{args.name}.csv'}")
    return tables, curves


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    throughput = commands.add_parser("throughput", help="seconds per primitive step relative to SAC+HER")
    throughput.add_argument("--env", default="PointMazeFourRooms-v0")
    throughput.add_argument("--steps", type=int, default=1000)
    throughput.add_argument("--repeats", type=int, default=5)
    throughput.add_argument("--net-arch", type=int, nargs="+", default=[256, 256])
    profiles = commands.add_parser("profiles", help="training steps/s at each task's CPU profile, vs the env and SAC+HER")
    profiles.add_argument("--envs", nargs="+", default=CPU_TASKS)
    profiles.add_argument("--algos", nargs="+", default=["dipper", "sac"])
    profiles.add_argument("--steps", type=int, default=1000)
    profiles.add_argument("--repeats", type=int, default=3)
    profiles.add_argument("--name", default="profiles")
    profiles.add_argument("--write", action="store_true", help="write the section of BENCHMARKS.md and the CSV")
    profiles.add_argument(
        "--fused-adam", action="store_true", help="also measure each algorithm with fused Adam optimizers (<algo>-fused)"
    )
    profiles.add_argument(
        "--variant",
        nargs="+",
        action="append",
        default=[],
        metavar="NAME KEY=VALUE",
        help="also measure each algorithm with these hyperparameters as <algo>-NAME (repeatable; values are literals, "
        "a dict updates the entry's dict)",
    )
    updates = commands.add_parser("updates", help="ms per lower and higher training update, vs SB3's SAC update")
    updates.add_argument("--env", default="FetchPickAndPlaceFixed-v0")
    updates.add_argument("--warmup", type=int, default=3000, help="primitive steps trained past learning_starts first")
    updates.add_argument("--updates", type=int, default=20, help="updates of each kind per round")
    updates.add_argument("--repeats", type=int, default=7, help="interleaved rounds; the median counts")
    learning = commands.add_parser("learning", help="success curves of algorithms x tasks x seeds")
    learning.add_argument("--protocol", choices=sorted(PROTOCOLS), help="preset algorithms, tasks, seeds and budgets")
    # Defaults (None) come from the protocol, then from LEARNING_DEFAULTS; see resolve_protocol.
    learning.add_argument("--envs", "--env", nargs="+", help=f"tasks (default: {POINT_MAZE})")
    learning.add_argument("--algos", nargs="+", help=f"zoo names (default: {' '.join(LEARNING_DEFAULTS['algos'])})")
    learning.add_argument("--seeds", type=int, nargs="+", help=f"default: {LEARNING_DEFAULTS['seeds']}")
    learning.add_argument("--eval-freq", type=int, help=f"default: {LEARNING_DEFAULTS['eval_freq']} primitive steps")
    learning.add_argument("--eval-episodes", type=int, help=f"default: {LEARNING_DEFAULTS['eval_episodes']}")
    learning.add_argument("--n-eval-envs", type=int, help="evaluation envs (default: --eval-episodes, at most 10)")
    learning.add_argument("--n-timesteps", type=int, help="override every entry's n_timesteps (the zoo's -n)")
    learning.add_argument("--workers", type=int, default=2, help="runs at a time on this machine")
    learning.add_argument("--ray-address", help="run on this Ray cluster (e.g. 10.0.0.1:6379 or auto) instead")
    learning.add_argument(
        "--pause-after-minutes",
        type=float,
        help="pause each run after this many minutes of training with a resume checkpoint; the same command resumes it",
    )
    learning.add_argument(
        "--save-freq",
        type=int,
        help="also keep the model every this many primitive steps (rl-zoo3's rl_model_<steps>_steps.zip in the run "
        "folder), e.g. for zoo_scripts/planner_share.py --checkpoints",
    )
    learning.add_argument("--out", default="runs/benchmark", help="runs in <out>/<variant>/seed_<n>/, tables, CSV, figure")
    learning.add_argument("--name", help="section of BENCHMARKS.md, figure and CSV name (default: protocol or learning)")
    learning.add_argument(
        "--variant", default=None, help=f"name of a variant: its runs live in <out>/<variant> (else <out>/{DEFAULT_VARIANT})"
    )
    learning.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="hyperparameters: the zoo's -params")
    learning.add_argument("--env-kwargs", nargs="*", default=[], metavar="KEY=VALUE", help="the zoo's --env-kwargs")
    learning.add_argument(
        "--report-only", action="store_true", help="run nothing: tables and figure from the runs on disk, partial ones too"
    )
    learning.add_argument("--report", nargs="*", default=None, help="runs to put in the table (default: this command's)")
    learning.add_argument(
        "--previous-csv",
        help="an earlier report's CSV (e.g. docs/benchmarks/<name>.csv): its runs count where --out has no run folder",
    )
    learning.add_argument("--write", action="store_true", help="write the section of BENCHMARKS.md and its figure")
    learning.add_argument("--benchmarks-md", help="with --write: the markdown file of the section (default: BENCHMARKS.md)")
    learning.add_argument("--figures-dir", help="with --write: the directory of the figure (default: docs/benchmarks)")
    args = parser.parse_args()
    if args.command == "learning":
        if not args.write and (args.benchmarks_md or args.figures_dir):
            learning.error("--benchmarks-md and --figures-dir say where --write writes: add --write, or leave them out")
        if args.previous_csv and not Path(args.previous_csv).is_file():
            learning.error(f"--previous-csv {args.previous_csv}: no such file (a CSV an earlier report wrote)")
        if args.variant == DEFAULT_VARIANT:
            learning.error(f"--variant {DEFAULT_VARIANT} names the folder of the runs without a variant: choose another")
    commands_run = {"throughput": run_throughput, "profiles": run_profiles, "updates": run_updates, "learning": run_learning}
    commands_run[args.command](args)


if __name__ == "__main__":
    main()
