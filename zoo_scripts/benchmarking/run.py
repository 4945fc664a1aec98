"""``benchmark.py learning``: every (algorithm, task, seed) run as an ``sb3-dipper-zoo train`` process of its own,
here or on a Ray cluster, resumed where it paused and marked finished with ``result.json``; the protocols' presets.

``zoo_scripts/benchmark.py`` is the command line; its docstring describes the runs and their folders.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import plot
from configs import torch_threads

from sb3_dipper.common.files import write_bytes_atomically
from sb3_dipper.zoo.resume import RESUME_FOLDER, RESUME_MODEL, saved_steps

from . import SCRIPTS

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
PAPER_ALGORITHMS = [
    "dipper",
    "dipper_paper",
    "dipper_nov",
    "hier",
    "hac",
    "raps",
    "piper",
    "saga",
    "dac",
    "dpo_flat",
    "sac",
    "sac_demo",
]
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

    rl-zoo3 evaluates each value as Python. A bare word such as ``preference_source=progress`` would be a name it cannot
    evaluate (in every run, after its start-up), so it is refused here with the quoting that works.

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


def run_steps_per_second(run: Path) -> float | None:
    """A finished run's primitive steps per second of wall time, evaluations and every part of a paused run included
    (``result.json``'s seconds), or None before it finished."""
    steps = model_steps(run)
    if not finished(run) or steps is None:
        return None
    seconds = float(json.loads((run / RESULT).read_text())["seconds"])
    return steps[0] / seconds if seconds > 0 else None


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


def ray_runtime_env() -> dict[str, Any]:
    """The runtime environment of the runs' Ray tasks: this checkout's scripts on their path, this process's MuJoCo
    backend and torch threads, and the niceness of the node's Ray processes (0 where started as usual)."""
    # Workers unpickle learning_run (benchmarking.run), which imports configs and plot: the scripts' folder must be on
    # their path.
    python_path = [str(SCRIPTS), *filter(None, [os.environ.get("PYTHONPATH")])]
    # Ray renices its task workers to 15 and the zoo process of a run inherits it, so beside any other load the training
    # starves (a 12-second run took 2.2 minutes beside two trainings); Ray's own job supervisor asks for 0 the same way.
    env_vars = {
        "PYTHONPATH": os.pathsep.join(python_path),
        "MUJOCO_GL": os.environ["MUJOCO_GL"],
        "RAY_worker_niceness": "0",
    }
    if "SB3_DIPPER_THREADS" in os.environ:
        env_vars["SB3_DIPPER_THREADS"] = os.environ["SB3_DIPPER_THREADS"]
    return {"env_vars": env_vars}


def ray_results(jobs: list[tuple[Any, ...]], address: str) -> Iterator[str]:
    """The runs as Ray tasks of one CPU on the cluster at ``address``; they write into ``--out`` themselves."""
    import ray

    ray.init(address=address, runtime_env=ray_runtime_env())
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
