"""Benchmarks: throughput ratios and learning curves, written to BENCHMARKS.md with command, machine and date.

    python zoo_scripts/benchmark.py throughput                      # DIPPER/HIER seconds per step vs SB3 SAC+HER
    python zoo_scripts/benchmark.py learning --algos dipper hier sac --seeds 0 1 2 --workers 2
    python zoo_scripts/benchmark.py learning --algos dipper --variant no-planning --set planning=off --name ablations

``learning`` runs every (algorithm, seed) pair from its ``hyperparams/<algo>.yml`` entry in a process pool, evaluates
the deterministic success rate every ``--eval-freq`` primitive steps (``evaluations.npz`` per run), skips runs that
already finished (rerun after a crash to resume), and aggregates: a CSV, a markdown table and a success-curve figure
(mean and standard deviation over seeds).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import random
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

sys.path.insert(0, str(Path(__file__).resolve().parent))
from configs import episode_successes, load_entry, make_env, make_model, torch_threads

REPO = Path(__file__).resolve().parent.parent
BENCHMARKS_MD = REPO / "BENCHMARKS.md"
RESULTS_DIR = REPO / "docs" / "benchmarks"
LABELS = {"dipper": "DIPPER", "dipper_paper": "DIPPER (paper)", "hier": "HIER", "sac": "SAC+HER", "tqc": "TQC+HER"}


# ------------------------------------------------------------------------------------------------------------- report


def label(run: str) -> str:
    algo, _, variant = run.partition("-")
    return LABELS.get(algo, algo) + (f" ({variant})" if variant else "")


def machine() -> str:
    return f"{os.cpu_count()} cores, {platform.processor() or platform.machine()}, torch {th.__version__}, no GPU"


def write_section(name: str, body: str, command: str) -> None:
    """Replace (or append) the ``name`` section of BENCHMARKS.md, stamped with command, machine and date."""
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    stamp = f"Command: `{command}`  \nMachine: {machine()}  \nDate: {datetime.date.today().isoformat()}\n\n"
    section = f"{start}\n{stamp}{body.strip()}\n{end}"
    text = BENCHMARKS_MD.read_text() if BENCHMARKS_MD.exists() else "# Benchmarks\n"
    if start in text and end in text:
        text = text[: text.index(start)] + section + text[text.index(end) + len(end) :]
    else:
        text = f"{text.rstrip()}\n\n{section}\n"
    BENCHMARKS_MD.write_text(text)


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


# ------------------------------------------------------------------------------------------------------------- learning


class PeriodicSuccess(BaseCallback):
    """Deterministic success rate every ``eval_freq`` primitive steps, saved as ``evaluations.npz`` (EvalCallback keys)."""

    def __init__(self, eval_env, eval_freq: int, n_episodes: int, path: Path):
        super().__init__()
        self.eval_env, self.eval_freq, self.n_episodes, self.path = eval_env, eval_freq, n_episodes, path
        self.timesteps: list[int] = []
        self.successes: list[list[float]] = []
        self._next = eval_freq

    def _on_step(self) -> bool:
        if self.num_timesteps >= self._next:
            self._next += self.eval_freq
            self.evaluate()
        return True

    def evaluate(self) -> None:
        self.timesteps.append(self.num_timesteps)
        self.successes.append(episode_successes(self.model, self.eval_env, self.n_episodes))
        np.savez(self.path, timesteps=np.array(self.timesteps), successes=np.array(self.successes))


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
    """One (algorithm, seed) run; writes evaluations.npz and, once finished, result.json."""
    th.set_num_threads(torch_threads())
    directory = run_directory(out, run_name(algo, variant), env_id, seed)
    directory.mkdir(parents=True, exist_ok=True)
    model, _, budget = make_model(algo, env_id, seed=seed, overrides=overrides)
    budget = n_timesteps or budget
    eval_env = make_env(env_id, load_entry(algo, env_id), seed=seed + 10_000, n_envs=10)
    callback = PeriodicSuccess(eval_env, eval_freq, eval_episodes, directory / "evaluations.npz")
    start = time.time()
    model.learn(budget, callback=callback)
    if not callback.timesteps or callback.timesteps[-1] < model.num_timesteps:
        callback.evaluate()
    seconds = time.time() - start
    result = dict(
        algo=algo, variant=variant, overrides=overrides, env=env_id, seed=seed, steps=model.num_timesteps, seconds=seconds
    )
    (directory / "result.json").write_text(json.dumps(result))
    return f"{algo} seed {seed}: {seconds / 60:.1f} min, final success {np.mean(callback.successes[-1]):.2f}"


def aggregate(out: Path, algos: list[str], env_id: str, seeds: list[int]) -> tuple[str, dict[str, Any]]:
    """Markdown table (final success mean +- std, steps to 50 %) and per-algorithm curves."""
    curves: dict[str, Any] = {}
    rows, csv_lines = [], ["algo,seed,timesteps,success"]
    for algo in algos:
        per_seed = []
        for seed in seeds:
            path = run_directory(out, algo, env_id, seed) / "evaluations.npz"
            if not path.exists():
                continue
            data = np.load(path)
            success = data["successes"].mean(axis=1)
            per_seed.append((data["timesteps"], success))
            csv_lines += [f"{algo},{seed},{int(t)},{s:.4f}" for t, s in zip(data["timesteps"], success, strict=True)]
        if not per_seed:
            continue
        length = min(len(steps) for steps, _ in per_seed)
        steps = per_seed[0][0][:length]
        matrix = np.stack([success[:length] for _, success in per_seed])
        curves[algo] = (steps, matrix)
        final = matrix[:, -1]
        mean_curve = matrix.mean(axis=0)
        reached = np.flatnonzero(mean_curve >= 0.5)
        to_half = f"{int(steps[reached[0]]):,}" if reached.size else "not reached"
        rows.append(f"| {label(algo)} | {len(per_seed)} | {final.mean():.2f} +- {final.std():.2f} | {to_half} |")
    (out / f"{env_id}_summary.csv").write_text("\n".join(csv_lines) + "\n")
    table = "| algorithm | seeds | final success (mean +- std) | steps to 50 % (mean curve) |\n|---|---|---|---|\n"
    return table + "\n".join(rows), curves


def plot_curves(curves: dict[str, Any], env_id: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for algo, (steps, matrix) in curves.items():
        mean, std = matrix.mean(axis=0), matrix.std(axis=0)
        ax.plot(steps, mean, label=label(algo))
        ax.fill_between(steps, np.clip(mean - std, 0, 1), np.clip(mean + std, 0, 1), alpha=0.2)
    ax.set(xlabel="primitive steps", ylabel="success rate (deterministic)", ylim=(-0.02, 1.02), title=env_id)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def run_learning(args: argparse.Namespace) -> None:
    out = Path(args.out)
    overrides = parse_overrides(args.set)
    names = [run_name(algo, args.variant) for algo in args.algos]
    todo = [
        (algo, seed)
        for algo in args.algos
        for seed in args.seeds
        if not (run_directory(out, run_name(algo, args.variant), args.env, seed) / "result.json").exists()
    ]
    print(f"{len(todo)} runs to do, {len(args.algos) * len(args.seeds) - len(todo)} already finished")
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        futures = [
            pool.submit(
                learning_run,
                *(algo, args.env, seed, out, args.eval_freq, args.eval_episodes, args.n_timesteps, args.variant, overrides),
            )
            for algo, seed in todo
        ]
        for future in futures:
            print(future.result(), flush=True)
    table, curves = aggregate(out, args.report or names, args.env, args.seeds)
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    figure = RESULTS_DIR / f"{args.name}.png"
    plot_curves(curves, args.env, figure)
    body = (
        f"`{args.env}`, seeds {args.seeds}, deterministic success over {args.eval_episodes} episodes every "
        f"{args.eval_freq} primitive steps; hyperparameters: the `{args.env}` entries of `hyperparams/<algo>.yml`.\n\n"
        f"{table}\n\n![success curves]({figure.relative_to(REPO)})"
    )
    write_section(args.name, body, "python zoo_scripts/benchmark.py learning " + " ".join(sys.argv[2:]))
    print(body)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    throughput = commands.add_parser("throughput", help="seconds per primitive step relative to SAC+HER")
    throughput.add_argument("--env", default="PointMazeFourRooms-v0")
    throughput.add_argument("--steps", type=int, default=1000)
    throughput.add_argument("--repeats", type=int, default=5)
    throughput.add_argument("--net-arch", type=int, nargs="+", default=[256, 256])
    learning = commands.add_parser("learning", help="success curves of algorithms x seeds")
    learning.add_argument("--env", default="PointMazeFourRooms-v0")
    learning.add_argument("--algos", nargs="+", default=["dipper", "hier", "sac"])
    learning.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    learning.add_argument("--workers", type=int, default=2)
    learning.add_argument("--eval-freq", type=int, default=20_000)
    learning.add_argument("--eval-episodes", type=int, default=50)
    learning.add_argument("--n-timesteps", type=int, default=None, help="override every entry's n_timesteps")
    learning.add_argument("--out", default="runs/benchmark")
    learning.add_argument("--name", default="learning", help="section of BENCHMARKS.md and figure name")
    learning.add_argument("--variant", default=None, help="name of a variant; its runs live in <algo>-<variant>")
    learning.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="hyperparameter overrides of a variant")
    learning.add_argument("--report", nargs="*", default=None, help="runs to put in the table (default: this command's)")
    args = parser.parse_args()
    {"throughput": run_throughput, "learning": run_learning}[args.command](args)


if __name__ == "__main__":
    main()
