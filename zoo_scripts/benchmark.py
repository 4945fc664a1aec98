"""Benchmarks: throughput ratios and learning curves, written to BENCHMARKS.md with command, machine and date.

    python zoo_scripts/benchmark.py throughput                      # DIPPER/HIER seconds per step vs SB3 SAC+HER
    python zoo_scripts/benchmark.py profiles --write                # steps/s at the paper tasks' CPU profiles
    python zoo_scripts/benchmark.py learning --algos dipper hier sac --seeds 0 1 2 --workers 2
    python zoo_scripts/benchmark.py learning --algos dipper --variant no-planning --set planning=off --name ablations
    python zoo_scripts/benchmark.py learning --protocol quick --out runs/quick            # every algorithm, <= 1 h
    python zoo_scripts/benchmark.py learning --protocol paper --ray-address HEAD:6379     # paper tasks on a cluster
    python zoo_scripts/benchmark.py learning --envs FetchPush-v4 FetchPickAndPlace-v4 --algos dipper sac --seeds 0 1

``learning`` runs every (algorithm, task, seed) triple from the task's entry of ``hyperparams/<algo>.yml``, evaluates
the deterministic success rate every ``--eval-freq`` primitive steps (``evaluations.npz`` per run, in
``<out>/<algo>/<env>/seed_<n>/``), skips runs that already finished (their ``result.json`` exists: rerun the same
command after a crash to resume), and aggregates: a CSV with an env column, one markdown table per task (final
success mean +- std, steps to 50 %, and for hierarchical algorithms the final subgoal distance and lower-level value)
and one figure with a panel per task (mean and standard deviation over seeds, a line per algorithm).

Runs execute in a local process pool of ``--workers`` processes, or with ``--ray-address`` as Ray tasks of one CPU
each on a running cluster (``ray start --head`` on one machine, ``ray start --address HEAD:6379`` on the others).
The Ray workers import this checkout and write into ``--out`` themselves, so every node must see the checkout, its
virtualenv and ``--out`` at the same paths (a shared filesystem) and run ``ray`` from that virtualenv
(``pip install -e ".[cluster]"``).

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
import datetime
import json
import math
import os
import platform
import random
import statistics
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.utils import safe_mean
from stable_baselines3.common.vec_env import VecNormalize, sync_envs_normalization

from sb3_dipper.common.hierarchical import HierarchicalAlgorithm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from configs import episode_successes, load_entry, make_env, make_model, torch_threads
from plot import LABELS

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
# Logged by the option layer of hierarchical algorithms (``rollout/<key>``); recorded at each evaluation.
OPTION_METRICS = ("subgoal_distance", "low_value")


# ------------------------------------------------------------------------------------------------------------- report


def label(run: str) -> str:
    algo, _, variant = run.partition("-")
    return LABELS.get(algo, algo) + (f" ({variant})" if variant else "")


def machine() -> str:
    return f"{os.cpu_count()} cores, {platform.processor() or platform.machine()}, torch {th.__version__}, no GPU"


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
    path.write_text(text)


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


def run_throughput(args: argparse.Namespace) -> None:
    th.set_num_threads(torch_threads())
    models = throughput_models(args.env, args.net_arch)
    for model in models.values():
        model.learn(THROUGHPUT_LOWER["learning_starts"] + args.steps)
    seconds: dict[str, list[float]] = {algo: [] for algo in models}
    order = list(models)
    for _ in range(args.repeats):
        random.shuffle(order)
        for algo in order:
            start = time.perf_counter()
            models[algo].learn(args.steps, reset_num_timesteps=False)
            seconds[algo].append((time.perf_counter() - start) / args.steps)
    per_step = {algo: statistics.median(values) for algo, values in seconds.items()}
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    (RESULTS_DIR / "throughput.json").write_text(json.dumps({"seconds_per_step": seconds, "median": per_step}, indent=1))
    rows = [f"| {LABELS[algo]} | {per_step[algo] * 1e3:.2f} | {per_step[algo] / per_step['sac']:.2f} |" for algo in models]
    body = (
        f"Seconds per primitive step on `{args.env}`, one env, lower networks {args.net_arch}, batch 256, one lower "
        f"gradient step per primitive step for every algorithm (SAC+HER: its only level). Median of {args.repeats} "
        f"interleaved chunks of {args.steps} steps after warm-up, measured in one process.\n\n"
        "| algorithm | ms per step | ratio to SAC+HER |\n|---|---|---|\n" + "\n".join(rows)
    )
    write_section("throughput", body, "python zoo_scripts/benchmark.py throughput " + " ".join(sys.argv[2:]))
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


def run_profiles(args: argparse.Namespace) -> None:
    """Training steps per second of each algorithm at each task's CPU profile, beside the env's own step rate.

    The models of one task are warmed up past ``learning_starts``, then trained in interleaved chunks of
    ``--steps`` primitive steps (the median chunk counts), in this one process, so the ratios share the machine's state.
    """
    th.set_num_threads(torch_threads())
    rows, records = [], []
    for env_id in args.envs:
        models = {algo: make_model(algo, env_id, seed=0)[0] for algo in args.algos}
        n_envs = models[args.algos[0]].n_envs
        env_rate = env_steps_per_second(env_id, n_envs, args.steps)
        for model in models.values():
            model.learn(int(getattr(model, "learning_starts", 0)) + args.steps)
        seconds: dict[str, list[float]] = {algo: [] for algo in models}
        order = list(models)
        for _ in range(args.repeats):
            random.shuffle(order)
            for algo in order:
                start = time.perf_counter()
                models[algo].learn(args.steps, reset_num_timesteps=False)
                seconds[algo].append(time.perf_counter() - start)
        rates = {algo: args.steps / statistics.median(values) for algo, values in seconds.items()}
        baseline = rates.get("sac")
        for algo, rate in rates.items():
            versus_sac = f"{rate / baseline:.2f}" if baseline else "-"
            ratios = f"{rate / env_rate:.2f} | {versus_sac}"
            rows.append(f"| `{env_id}` | {LABELS[algo]} | {rate:.0f} | {env_rate:.0f} | {ratios} |")
            records.append(f"{env_id},{algo},{n_envs},{rate:.2f},{env_rate:.2f}")
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
        RESULTS_DIR.mkdir(parents=True, exist_ok=True)
        csv.write_text("env,algo,n_envs,train_steps_per_second,env_steps_per_second\n" + "\n".join(records) + "\n")
        write_section(args.name, body, "python zoo_scripts/benchmark.py profiles " + " ".join(sys.argv[2:]))
    print(body)


# ------------------------------------------------------------------------------------------------------------- learning


class PeriodicSuccess(BaseCallback):
    """Deterministic success rate every ``eval_freq`` primitive steps, saved as ``evaluations.npz`` (EvalCallback keys).

    For hierarchical models it also saves, per evaluation, the mean subgoal distance and lower-level value of the
    last options: the values the model logs as ``rollout/subgoal_distance`` and ``rollout/low_value`` (NaN while
    none were recorded, e.g. the lower value before ``learning_starts`` or for a scripted lower level).
    """

    def __init__(self, eval_env, eval_freq: int, n_episodes: int, path: Path):
        super().__init__()
        self.eval_env, self.eval_freq, self.n_episodes, self.path = eval_env, eval_freq, n_episodes, path
        self.timesteps: list[int] = []
        self.successes: list[list[float]] = []
        self.option_metrics: dict[str, list[float]] = {key: [] for key in OPTION_METRICS}
        self._next = eval_freq

    def _on_step(self) -> bool:
        if self.num_timesteps >= self._next:
            self._next += self.eval_freq
            self.evaluate()
        return True

    def evaluate(self) -> None:
        # A model trained on a VecNormalize env is evaluated with the training statistics, frozen (as EvalCallback does).
        sync_envs_normalization(self.training_env, self.eval_env)
        self.timesteps.append(self.num_timesteps)
        self.successes.append(episode_successes(self.model, self.eval_env, self.n_episodes))
        arrays: dict[str, Any] = dict(timesteps=np.array(self.timesteps), successes=np.array(self.successes))
        if isinstance(self.model, HierarchicalAlgorithm):
            # The logger's values are cleared at every dump; these windows are what dump_logs averages.
            for key, values in self.option_metrics.items():
                values.append(float(safe_mean(self.model._option_metrics[key])))
                arrays[key] = np.array(values)
        np.savez(self.path, **arrays)


def run_name(algo: str, variant: str | None) -> str:
    return algo if variant is None else f"{algo}-{variant}"


def parse_overrides(assignments: list[str]) -> dict[str, Any]:
    """``key=value`` pairs, values read as YAML (``planning=off``, ``nll_coef=0.0``, ``hindsight_actions=false``)."""
    import yaml

    overrides = {}
    for assignment in assignments:
        key, separator, value = assignment.partition("=")
        if not separator:
            raise ValueError(f"--set takes key=value, got {assignment!r}")
        overrides[key] = yaml.safe_load(value)
    return overrides


def run_directory(out: Path, algo: str, env_id: str, seed: int) -> Path:
    return out / algo / env_id / f"seed_{seed}"


def learning_run(
    algo: str,
    env_id: str,
    seed: int,
    out: Path,
    eval_freq: int,
    eval_episodes: int,
    n_timesteps: int | None,
    variant: str | None = None,
    overrides: dict[str, Any] | None = None,
) -> str:
    """One (algorithm, task, seed) run; writes evaluations.npz and, once finished, result.json."""
    th.set_num_threads(torch_threads())
    directory = run_directory(out, run_name(algo, variant), env_id, seed)
    directory.mkdir(parents=True, exist_ok=True)
    model, _, budget = make_model(algo, env_id, seed=seed, overrides=overrides)
    budget = n_timesteps or budget
    eval_env = make_env(env_id, {**load_entry(algo, env_id), **(overrides or {})}, seed=seed + 10_000, n_envs=10)
    if isinstance(eval_env, VecNormalize):
        eval_env.training, eval_env.norm_reward = False, False
    callback = PeriodicSuccess(eval_env, eval_freq, eval_episodes, directory / "evaluations.npz")
    start = time.time()
    model.learn(budget, callback=callback)
    if not callback.timesteps or callback.timesteps[-1] < model.num_timesteps:
        callback.evaluate()
    seconds = time.time() - start
    model.save(directory / "model.zip")
    if isinstance(model.get_env(), VecNormalize):
        model.get_env().save(str(directory / "vecnormalize.pkl"))  # type: ignore[union-attr]
    result = dict(
        algo=algo, variant=variant, overrides=overrides, env=env_id, seed=seed, steps=model.num_timesteps, seconds=seconds
    )
    (directory / "result.json").write_text(json.dumps(result))
    return f"{algo} {env_id} seed {seed}: {seconds / 60:.1f} min, final success {np.mean(callback.successes[-1]):.2f}"


@dataclass
class Curves:
    """The evaluations of one algorithm on one task, truncated to the evaluations every seed has reached."""

    seeds: list[int]
    finished: list[bool]  # per seed: the run has ended (result.json); a running or cut-off run is partial
    steps: np.ndarray  # (evaluations,) primitive steps
    success: np.ndarray  # (seeds, evaluations) success rates
    metrics: dict[str, np.ndarray]  # every OPTION_METRICS key, (seeds, evaluations), NaN where not recorded


def load_curves(out: Path, algo: str, env_id: str, seeds: list[int]) -> Curves | None:
    runs = {}
    for seed in seeds:
        path = run_directory(out, algo, env_id, seed) / "evaluations.npz"
        if path.exists():
            with np.load(path) as data:
                runs[seed] = {key: data[key] for key in data.files}
    if not runs:
        return None
    length = min(len(run["timesteps"]) for run in runs.values())
    nan = np.full(length, np.nan)
    return Curves(
        seeds=list(runs),
        finished=[(run_directory(out, algo, env_id, seed) / "result.json").exists() for seed in runs],
        steps=next(iter(runs.values()))["timesteps"][:length],
        success=np.stack([run["successes"].mean(axis=1)[:length] for run in runs.values()]),
        metrics={key: np.stack([run[key][:length] if key in run else nan for run in runs.values()]) for key in OPTION_METRICS},
    )


def final_mean(curves: Curves, key: str) -> str:
    """Mean over seeds of a metric's last evaluation, or a dash where the algorithm does not record it."""
    final = curves.metrics[key][:, -1]
    return "-" if np.isnan(final).all() else f"{np.nanmean(final):.2f}"


def aggregate(out: Path, algos: list[str], env_id: str, seeds: list[int]) -> tuple[str, dict[str, Curves], list[str]]:
    """Markdown table of one task (final success mean +- std, steps to 50 %, option metrics), curves and CSV rows."""
    curves: dict[str, Curves] = {}
    rows, csv_rows = [], []
    for algo in algos:
        algo_curves = load_curves(out, algo, env_id, seeds)
        if algo_curves is None:
            continue
        curves[algo] = algo_curves
        for index, seed in enumerate(algo_curves.seeds):
            for step_index, step in enumerate(algo_curves.steps):
                metrics = [algo_curves.metrics[key][index, step_index] for key in OPTION_METRICS]
                values = ",".join("" if np.isnan(value) else f"{value:.4f}" for value in metrics)
                csv_rows.append(f"{env_id},{algo},{seed},{int(step)},{algo_curves.success[index, step_index]:.4f},{values}")
        final = algo_curves.success[:, -1]
        reached = np.flatnonzero(algo_curves.success.mean(axis=0) >= 0.5)
        to_half = f"{int(algo_curves.steps[reached[0]]):,}" if reached.size else "not reached"
        unfinished = algo_curves.finished.count(False)
        runs = f"{len(algo_curves.seeds)}" + (f" ({unfinished} partial)" if unfinished else "")
        rows.append(
            f"| {label(algo)} | {runs} | {int(algo_curves.steps[-1]):,} | {final.mean():.2f} +- {final.std():.2f} | "
            f"{to_half} | "
            f"{final_mean(algo_curves, 'subgoal_distance')} | {final_mean(algo_curves, 'low_value')} |"
        )
    table = (
        "| algorithm | seeds | last evaluation (steps) | success there (mean +- std) | steps to 50 % (mean curve) | "
        "subgoal distance there | lower value there |\n|---|---|---|---|---|---|---|\n"
    )
    return table + "\n".join(rows), curves, csv_rows


def plot_curves(curves: dict[str, dict[str, Curves]], path: Path) -> dict[str, list[str]]:
    """One panel per task, a line per algorithm (mean, band of one standard deviation); returns each panel's lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    algos = list(dict.fromkeys(algo for task in curves.values() for algo in task))
    # The same colour for an algorithm in every panel: tab20's even colours are tab10's, its lighter odd ones serve
    # past the tenth algorithm (the full comparison has eleven).
    colormap = plt.get_cmap("tab20")
    colors = {algo: colormap((2 * index) % 20 + (2 * index) // 20) for index, algo in enumerate(algos)}
    columns = 1 if len(curves) == 1 else 2
    rows = math.ceil(len(curves) / columns)
    fig, axes = plt.subplots(rows, columns, figsize=(6.5 * columns, 4 * rows), squeeze=False, layout="constrained")
    lines = {}
    for ax, (env_id, task) in zip(axes.flat, curves.items(), strict=False):
        for algo, algo_curves in task.items():
            mean, std = algo_curves.success.mean(axis=0), algo_curves.success.std(axis=0)
            ax.plot(algo_curves.steps, mean, label=label(algo), color=colors[algo])
            ax.fill_between(
                algo_curves.steps, np.clip(mean - std, 0, 1), np.clip(mean + std, 0, 1), color=colors[algo], alpha=0.2
            )
        ax.set(xlabel="primitive steps", ylabel="success rate (deterministic)", ylim=(-0.02, 1.02), title=env_id)
        ax.grid(alpha=0.3)
        lines[env_id] = [line.get_label() for line in ax.get_lines()]
    for ax in axes.flat[len(curves) :]:
        ax.set_axis_off()
    handles = [plt.Line2D([], [], color=colors[algo], label=label(algo)) for algo in algos]
    fig.legend(handles=handles, loc="outside right upper")
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return lines


def report(
    out: Path, algos: list[str], envs: list[str], seeds: list[int], name: str, figures_dir: Path
) -> tuple[dict[str, str], dict[str, dict[str, Curves]], Path]:
    """Tables and curves per task, the CSV ``<out>/<name>.csv`` and the figure ``<figures_dir>/<name>.png``."""
    tables, curves, csv_rows = {}, {}, ["env,algo,seed,timesteps,success," + ",".join(OPTION_METRICS)]
    for env_id in envs:
        tables[env_id], curves[env_id], rows = aggregate(out, algos, env_id, seeds)
        csv_rows += rows
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.csv").write_text("\n".join(csv_rows) + "\n")
    figures_dir.mkdir(parents=True, exist_ok=True)
    figure = figures_dir / f"{name}.png"
    plot_curves(curves, figure)
    return tables, curves, figure


def local_results(jobs: list[tuple[Any, ...]], workers: int) -> Iterator[str]:
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futures = [pool.submit(learning_run, *job) for job in jobs]
        for future in as_completed(futures):
            yield future.result()


def ray_results(jobs: list[tuple[Any, ...]], address: str) -> Iterator[str]:
    """The runs as Ray tasks of one CPU on the cluster at ``address``; they write into ``--out`` themselves."""
    import ray

    # Workers unpickle learning_run, which imports configs from this directory: it must be on their path.
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
    overrides = parse_overrides(args.set)
    names = [run_name(algo, args.variant) for algo in args.algos]
    triples = [(algo, env_id, seed) for algo in args.algos for env_id in args.envs for seed in args.seeds]
    jobs = [
        (algo, env_id, seed, out, args.eval_freq, args.eval_episodes, args.n_timesteps, args.variant, overrides)
        for algo, env_id, seed in triples
        if not (run_directory(out, run_name(algo, args.variant), env_id, seed) / "result.json").exists()
    ]
    print(f"{len(jobs)} runs to do, {len(triples) - len(jobs)} already finished", flush=True)
    if not args.report_only:
        results = ray_results(jobs, args.ray_address) if args.ray_address else local_results(jobs, args.workers)
        for result in results:
            print(result, flush=True)
    tables, curves, figure = report(out, args.report or names, args.envs, args.seeds, args.name, Path(args.figures_dir))
    markdown = Path(args.benchmarks_md)
    budget = f"{args.n_timesteps:,} primitive steps per run" if args.n_timesteps else "the YAML budgets"
    body = (
        f"Seeds {args.seeds}, {budget}, deterministic success over {args.eval_episodes} episodes every "
        f"{args.eval_freq:,} primitive steps; hyperparameters: each task's entry of `hyperparams/<algo>.yml`. Subgoal "
        "distance and lower value: mean of the last 100 options at the last evaluation (hierarchical algorithms).\n\n"
        + "\n\n".join(f"`{env_id}`\n\n{table}" for env_id, table in tables.items())
        + f"\n\n![success curves]({os.path.relpath(figure, markdown.resolve().parent)})"
    )
    write_section(args.name, body, "python zoo_scripts/benchmark.py learning " + " ".join(sys.argv[2:]), markdown)
    print(body)
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
    learning = commands.add_parser("learning", help="success curves of algorithms x tasks x seeds")
    learning.add_argument("--protocol", choices=sorted(PROTOCOLS), help="preset algorithms, tasks, seeds and budgets")
    # Defaults (None) come from the protocol, then from LEARNING_DEFAULTS; see resolve_protocol.
    learning.add_argument("--envs", "--env", nargs="+", help=f"tasks (default: {POINT_MAZE})")
    learning.add_argument("--algos", nargs="+", help=f"zoo names (default: {' '.join(LEARNING_DEFAULTS['algos'])})")
    learning.add_argument("--seeds", type=int, nargs="+", help=f"default: {LEARNING_DEFAULTS['seeds']}")
    learning.add_argument("--eval-freq", type=int, help=f"default: {LEARNING_DEFAULTS['eval_freq']} primitive steps")
    learning.add_argument("--eval-episodes", type=int, help=f"default: {LEARNING_DEFAULTS['eval_episodes']}")
    learning.add_argument("--n-timesteps", type=int, help="override every entry's n_timesteps")
    learning.add_argument("--workers", type=int, default=2, help="processes of the local pool")
    learning.add_argument("--ray-address", help="run on this Ray cluster (e.g. 10.0.0.1:6379 or auto) instead")
    learning.add_argument("--out", default="runs/benchmark")
    learning.add_argument("--name", help="section of BENCHMARKS.md, figure and CSV name (default: protocol or learning)")
    learning.add_argument("--variant", default=None, help="name of a variant; its runs live in <algo>-<variant>")
    learning.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="hyperparameter overrides of a variant")
    learning.add_argument(
        "--report-only", action="store_true", help="run nothing: tables and figure from the runs on disk, partial ones too"
    )
    learning.add_argument("--report", nargs="*", default=None, help="runs to put in the table (default: this command's)")
    learning.add_argument("--benchmarks-md", default=str(BENCHMARKS_MD), help="markdown file the section is written to")
    learning.add_argument("--figures-dir", default=str(RESULTS_DIR), help="directory of the figure")
    args = parser.parse_args()
    {"throughput": run_throughput, "profiles": run_profiles, "learning": run_learning}[args.command](args)


if __name__ == "__main__":
    main()
