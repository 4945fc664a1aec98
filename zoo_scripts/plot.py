"""Figures from rl-zoo3 log folders: success curves, hierarchical metrics and the IQM of the final success.

    python zoo_scripts/plot.py -f logs --algos dipper hier sac --envs PointMazeFourRooms-v0 --out figures/
    python zoo_scripts/plot.py -f logs --algos dipper hier sac --envs FetchPush-v4 FetchPickAndPlace-v4 --iqm --format png
    python zoo_scripts/plot.py -f runs/quick/default/seed_* --algos dipper sac --envs PointMazeFourRooms-v0   # benchmark

Runs are the zoo's folders ``<log_folder>/<algo>/<env_id>_<n>[_<uuid>]/``; the runs of one algorithm on one env in all
the ``-f`` folders are its seeds (``zoo_scripts/benchmark.py learning`` gives each seed its own log folder,
``<out>/<variant>/seed_<n>``). This module is the one reader of run folders: ``benchmark.py`` reports through its
loaders and draws its figure with :func:`draw_success`. Written to ``--out``:

- ``success.{png,pdf}`` (the look of Figure 2 of the DIPPER paper): success rate against primitive steps, mean and a
  standard-deviation band over seeds, one line per algorithm, one panel per env. The success rate comes from the
  deterministic evaluations of the zoo's ``EvalCallback`` (``evaluations.npz``, key ``successes``) when a run has them,
  otherwise from the training episodes' ``is_success`` in the monitor files, smoothed over ``--window`` episodes.
- ``hierarchical_metrics.{png,pdf}`` (Figure 3 of the paper): ``rollout/subgoal_distance`` and ``rollout/low_value``
  against steps from SB3's CSV logger (``progress.csv`` anywhere in a run folder); algorithms without them are left out.
- with ``--benchmark-csv FILE``, only ``hierarchical_metrics`` from a ``benchmark.py`` CSV (the committed record of a
  benchmark, whose run folders may be gone).
- with ``--iqm``, ``final_success_iqm.{png,pdf,csv}``: the interquartile mean of the final success over seeds with
  stratified-bootstrap 95 % confidence intervals (``rliable``), one bar per algorithm and env.
"""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import pandas as pd

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.artist import Artist
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter
from stable_baselines3.common.monitor import LoadMonitorResultsError, load_results

from sb3_dipper.common.files import read_npz, write_atomically, write_bytes_atomically
from sb3_dipper.zoo.callbacks import PROGRESS_FILE, STEPS_KEY, read_progress

# A curve: x (primitive steps) and y, one value per x.
Curve = tuple[np.ndarray, np.ndarray]

LABELS = {
    "dipper": "DIPPER",
    "dipper_paper": "DIPPER (paper)",
    "dipper_nov": "DIPPER-No-V",
    "hier": "HIER",
    "hac": "HAC",
    "dac": "DAC",
    "dpo_flat": "DPO-FLAT",
    "piper": "PIPER",
    "saga": "SAGA",
    "raps": "RAPS",
    "sac": "SAC+HER",
    "sac_demo": "SAC+HER+BC",
    "tqc": "TQC+HER",
}
HIERARCHICAL_METRICS = {"rollout/subgoal_distance": "distance to the subgoal", "rollout/low_value": "lower value"}


def label(name: str) -> str:
    """The legend name of an algorithm, or of ``<algo>-<variant>`` (a benchmark variant): ``DIPPER (no-planning)``."""
    algo, _, variant = name.partition("-")
    return LABELS.get(algo, algo) + (f" ({variant})" if variant else "")


def zoo_runs(log_folder: Path, algo: str, env_id: str) -> list[Path]:
    """The zoo's run folders ``<log_folder>/<algo>/<env_id>_<n>[_<uuid>]`` of ``algo`` on ``env_id``, in run order."""
    pattern = re.compile(rf"{re.escape(env_id)}_(\d+)(_.*)?")
    numbered = [(pattern.fullmatch(path.name), path) for path in (Path(log_folder) / algo).glob(f"{env_id}_*")]
    return [path for _, path in sorted((int(match[1]), path) for match, path in numbered if match and path.is_dir())]


def find_runs(log_folders: Sequence[Path], algo: str, env_id: str) -> list[Path]:
    """The runs of ``algo`` on ``env_id`` in every log folder (its seeds); a clear error when there are none."""
    runs = [run for folder in log_folders for run in zoo_runs(folder, algo, env_id)]
    if not runs:
        algo_folders = [Path(folder) / algo for folder in log_folders]
        searched = ", ".join(f"{folder}/" for folder in algo_folders)
        found = sorted({path.name for folder in algo_folders if folder.is_dir() for path in folder.iterdir()})
        raise FileNotFoundError(
            f"no runs of {algo} on {env_id} in {searched} (expected folders {env_id}_<n>; found {found or 'nothing'})"
        )
    return runs


def evaluation_curve(run: Path) -> Curve | None:
    """Deterministic success rate against primitive steps from the run's ``evaluations.npz`` (the ``successes`` that
    SB3's ``EvalCallback`` records when the env reports ``info["is_success"]``), or None before the first evaluation.

    :raises ValueError: the record is damaged (cut short, say) or lacks its ``timesteps``; the message names the file
    """
    evaluations = run / "evaluations.npz"
    if not evaluations.exists():
        return None
    fix = (
        "It is the run's record of its evaluations (SB3's EvalCallback): restore it from a copy of the run folder, or "
        "delete it to read the run's success from its monitor files."
    )
    data = read_npz(evaluations, "evaluation record", fix)
    if "successes" not in data or data["successes"].size == 0:
        return None
    if "timesteps" not in data or len(data["timesteps"]) != len(data["successes"]):
        raise ValueError(f"Malformed evaluation record {evaluations}: no timesteps for its successes. {fix}")
    return data["timesteps"].astype(float), data["successes"].mean(axis=1)


def success_curve(run: Path, window: int = 100) -> Curve:
    """Success rate against primitive steps of one run: its evaluations, else its smoothed training episodes."""
    evaluations = evaluation_curve(run)
    if evaluations is not None:
        return evaluations
    try:
        episodes = load_results(str(run))
    except LoadMonitorResultsError:
        episodes = None
    if episodes is None or "is_success" not in episodes or episodes.empty:
        raise FileNotFoundError(
            f"{run} has no success data: neither evaluations.npz with 'successes' (train with --eval-freq on an env "
            "that reports info['is_success']) nor monitor files with an is_success column "
            "(monitor_kwargs: dict(info_keywords=('is_success',)))"
        )
    # load_results merges the monitor files of all envs in time order, so the summed lengths count every env's steps.
    steps = episodes["l"].cumsum().to_numpy(dtype=float)
    success = episodes["is_success"].astype(float).rolling(window, min_periods=1).mean().to_numpy()
    return steps, success


def training_success_curve(run: Path, window: int = 100) -> Curve | None:
    """Success rate of the training episodes (the policy as it acts while learning, stochastic), over the last
    ``window`` episodes, against primitive steps: the authors' "train success rate". None without monitor files.

    A run trained in parts (``sb3-dipper-zoo train --pause-after-minutes``) has each earlier part's monitor files in
    ``part_<k>/``: the parts are read in order, each continuing the previous one's step count.
    """
    folders = [*sorted(run.glob("part_*"), key=lambda part: int(part.name.split("_")[1])), run]
    lengths, successes = [], []
    for folder in folders:
        try:
            episodes = load_results(str(folder))
        except LoadMonitorResultsError:
            continue
        if "is_success" in episodes and not episodes.empty:
            lengths.append(episodes["l"].to_numpy(dtype=float))
            successes.append(episodes["is_success"].to_numpy(dtype=float))
    if not lengths:
        return None
    steps = np.cumsum(np.concatenate(lengths))
    success = pd.Series(np.concatenate(successes)).rolling(window, min_periods=1).mean().to_numpy()
    return steps, success


def final_success(run: Path, window: int = 100) -> float:
    """The last point of a run's success curve: its last evaluation, or its last ``window`` training episodes."""
    return float(success_curve(run, window)[1][-1])


def align(curves: list[Curve], n_points: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """The seeds' curves at common steps: ``(steps, values)`` with ``values`` of shape ``(seeds, steps)``.

    Seeds measured at the same steps, some not as far yet (a run still going), keep the steps every seed has reached.
    Seeds measured at different steps are interpolated over the range every seed covers. Either way the mean never
    mixes a different number of seeds along the curve.
    """
    length = min(len(x) for x, _ in curves)
    if all(np.array_equal(x[:length], curves[0][0][:length]) for x, _ in curves):
        return curves[0][0][:length], np.stack([y[:length] for _, y in curves])
    start, end = max(x[0] for x, _ in curves), min(x[-1] for x, _ in curves)
    steps = np.linspace(start, end, n_points) if end > start else np.array([end])
    return steps, np.stack([np.interp(steps, x, y) for x, y in curves])


def aggregate(curves: list[Curve], n_points: int = 100) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and standard deviation over seeds at the steps :func:`align` keeps: ``(steps, mean, std)``."""
    steps, values = align(curves, n_points)
    return steps, values.mean(axis=0), values.std(axis=0)


def steps_label(steps: float, _position: object = None) -> str:
    """A primitive-step tick as people write budgets: 150k, 1.5M (full numbers ran into each other at 640k)."""
    if abs(steps) >= 1e6:
        return f"{steps / 1e6:g}M"
    return f"{steps / 1e3:g}k" if abs(steps) >= 1e3 else f"{steps:g}"


def steps_axis(ax: plt.Axes) -> None:
    """Primitive steps on the x axis of ``ax``, with ticks as :func:`steps_label` writes them."""
    ax.set_xlabel("primitive steps")
    ax.xaxis.set_major_formatter(FuncFormatter(steps_label))


def line_colors(names: list[str]) -> dict[str, tuple[float, ...]]:
    """One color per line name, the same in every panel and figure.

    tab20's even colors are tab10's (matplotlib's default cycle); its lighter odd ones serve past the tenth name (the
    full comparison has eleven algorithms).
    """
    colormap = plt.get_cmap("tab20")
    return {name: colormap((2 * index) % 20 + (2 * index) // 20) for index, name in enumerate(names)}


def _plot_series(ax: plt.Axes, steps: np.ndarray, values: np.ndarray, **kwargs: Any) -> None:
    """``ax.plot``, with a marker for a series of one point (a single evaluation), which a line alone leaves invisible."""
    ax.plot(steps, values, marker="o" if len(steps) == 1 else None, **kwargs)


def shared_legend(fig: Figure, axes: np.ndarray) -> None:
    """One legend below the panels (as in the paper's figures), with every algorithm that appears in any panel."""
    entries: dict[str, Artist] = {}
    for ax in axes.flat:
        for handle, text in zip(*ax.get_legend_handles_labels(), strict=True):
            entries.setdefault(text, handle)
    columns = max(1, min(len(entries), 6))
    # The figure grows by the legend's rows (a quarter inch each, and a margin) so that many entries never cover a panel.
    legend_height = 0.25 * math.ceil(len(entries) / columns) + 0.2
    width, height = fig.get_size_inches()
    fig.set_size_inches(width, height + legend_height)
    fig.tight_layout(rect=(0, legend_height / (height + legend_height), 1, 1))
    fig.legend(list(entries.values()), list(entries), loc="lower center", ncol=columns, frameon=False)


def draw_seeds(
    ax: plt.Axes, curves: list[Curve], color: tuple[float, ...], legend_text: str, limits: tuple[float, float] | None = None
) -> None:
    """One line of a panel from the seeds' curves: their mean with a band of one standard deviation (:func:`aggregate`)
    where every seed has been measured; seeds that went further (the others still running) go on as thin dotted lines.

    :param limits: the range the values can take (``(0, 1)`` for a rate), which the band does not leave
    """
    steps, mean, std = aggregate(curves)
    _plot_series(ax, steps, mean, color=color, label=legend_text)
    low, high = mean - std, mean + std
    if limits is not None:
        low, high = np.clip(low, *limits), np.clip(high, *limits)
    ax.fill_between(steps, low, high, color=color, alpha=0.2)
    for seed_steps, seed_values in curves:
        if seed_steps[-1] > steps[-1]:
            further = seed_steps >= steps[-1]
            _plot_series(ax, seed_steps[further], seed_values[further], color=color, linewidth=0.8, linestyle=":")


def draw_success(panels: dict[str, dict[str, list[Curve]]], labels: Callable[[str], str] = label) -> Figure:
    """Success rate against primitive steps, one panel per env (four to a row), one line per name in it.

    :param panels: per env id, the seeds' success curves of each line, keyed by algorithm (or ``<algo>-<variant>``)
        name; each line is the mean over seeds with a band of one standard deviation (:func:`aggregate`), where every
        seed has been measured; seeds that went further (the others still running) go on as thin dotted lines
    :param labels: the legend name of a line's key
    """
    names = list(dict.fromkeys(name for lines in panels.values() for name in lines))
    colors = line_colors(names)
    columns = min(len(panels), 4)
    rows = math.ceil(len(panels) / columns)
    fig, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 3.4 * rows), squeeze=False, sharey=True)
    for ax, (env_id, lines) in zip(axes.flat, panels.items(), strict=False):
        for name, curves in lines.items():
            draw_seeds(ax, curves, colors[name], labels(name), limits=(0, 1))
        ax.set(title=env_id, ylim=(-0.02, 1.02))
        steps_axis(ax)
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(panels) :]:
        ax.set_axis_off()
    for ax in axes[:, 0]:
        ax.set_ylabel("success rate")
    shared_legend(fig, axes)
    return fig


def plot_success(log_folders: Sequence[Path], algos: list[str], envs: list[str], window: int = 100) -> Figure:
    """Success rate against primitive steps: mean and standard-deviation band over seeds, one panel per env."""
    panels = {
        env_id: {algo: [success_curve(run, window) for run in find_runs(log_folders, algo, env_id)] for algo in algos}
        for env_id in envs
    }
    return draw_success(panels)


def load_progress(run: Path) -> pd.DataFrame | None:
    """The SB3 CSV log of a run (``progress.csv`` anywhere in its folder), or None when it has none.

    :raises ValueError: a ``progress.csv`` is damaged (:func:`~sb3_dipper.zoo.callbacks.read_progress`); the message
        names it, the line and the fix
    """
    files = sorted(run.rglob(PROGRESS_FILE))
    if not files:
        return None
    # A run resumed with `-i` writes a second log; concatenated in step order they form one curve.
    frames = [read_progress(path) for path in files]
    frames = [frame for frame in frames if STEPS_KEY in frame]
    return pd.concat(frames).sort_values(STEPS_KEY) if frames else None


def metric_curve(progress: pd.DataFrame, key: str) -> Curve | None:
    """``key`` against steps, where it was logged (``rollout/low_value`` starts only after ``learning_starts``)."""
    if key not in progress:
        return None
    logged = progress[[STEPS_KEY, key]].dropna()
    if logged.empty:
        return None
    return logged[STEPS_KEY].to_numpy(dtype=float), logged[key].to_numpy(dtype=float)


def value_at(curve: Curve | None, step: float) -> float:
    """The last value of a logged curve at or before ``step`` (NaN when nothing was logged by then)."""
    if curve is None:
        return math.nan
    logged = np.flatnonzero(curve[0] <= step)
    return float(curve[1][logged[-1]]) if logged.size else math.nan


def plot_hierarchical_metrics(log_folders: Sequence[Path], algos: list[str], envs: list[str]) -> Figure | None:
    """Distance to the subgoal and lower value against steps, one row per metric and one column per env.

    Flat algorithms log neither metric and are left out; returns None when no run has them.
    """

    def curves(env_id: str, algo: str, key: str) -> list[Curve]:
        logs = [load_progress(run) for run in find_runs(log_folders, algo, env_id)]
        return [curve for progress in logs if progress is not None and (curve := metric_curve(progress, key))]

    return draw_hierarchical_metrics(curves, algos, envs)


def benchmark_csv_curves(*csvs: Path) -> Callable[[str, str, str], list[Curve]]:
    """The per-seed curves of ``benchmark.py`` CSVs (env, algo, seed, timesteps, success, subgoal_distance, low_value),
    the committed records of benchmarks, keyed like progress.csv (``rollout/subgoal_distance``, ...)."""
    table = pd.concat([pd.read_csv(csv) for csv in csvs], ignore_index=True)

    def curves(env_id: str, algo: str, key: str) -> list[Curve]:
        column = key.removeprefix("rollout/")
        rows = table[(table["env"] == env_id) & (table["algo"] == algo)].dropna(subset=[column])
        return [(run["timesteps"].to_numpy(), run[column].to_numpy()) for _, run in rows.groupby("seed")]

    return curves


def draw_hierarchical_metrics(
    curves: Callable[[str, str, str], list[Curve]],
    algos: list[str],
    envs: list[str],
    labels: Callable[[str], str] = label,
) -> Figure | None:
    """The hierarchical-metrics figure from ``curves(env_id, algo, key)``, the per-seed curves of one metric.

    :param labels: the legend name of an algorithm (or ``<algo>-<variant>`` row label)
    """
    colors = line_colors(algos)
    n_rows = len(HIERARCHICAL_METRICS)
    fig, axes = plt.subplots(n_rows, len(envs), figsize=(4.2 * len(envs), 3.4 * n_rows), squeeze=False, sharey="row")
    plotted = False
    for col, env_id in enumerate(envs):
        for algo in algos:
            for row, key in enumerate(HIERARCHICAL_METRICS):
                seeds = curves(env_id, algo, key)
                if not seeds:
                    continue
                steps, mean, std = aggregate(seeds)
                ax = axes[row, col]
                _plot_series(ax, steps, mean, color=colors[algo], label=labels(algo))
                ax.fill_between(steps, mean - std, mean + std, color=colors[algo], alpha=0.2)
                plotted = True
        for row, name in enumerate(HIERARCHICAL_METRICS.values()):
            axes[row, col].set(title=env_id if row == 0 else None, ylabel=name if col == 0 else None)
            steps_axis(axes[row, col])
            axes[row, col].grid(alpha=0.3)
    if not plotted:
        plt.close(fig)
        return None
    shared_legend(fig, axes)
    return fig


def final_success_iqm(
    log_folders: Sequence[Path], algos: list[str], envs: list[str], window: int = 100, reps: int = 2000, seed: int = 0
) -> pd.DataFrame:
    """IQM of the final success over seeds with a stratified-bootstrap 95 % interval, per algorithm and env."""
    from rliable import library, metrics

    rows = []
    for env_id in envs:
        # rliable expects (runs, tasks) score matrices; each env is estimated on its own, as one task.
        scores = {
            algo: np.array([[final_success(run, window)] for run in find_runs(log_folders, algo, env_id)]) for algo in algos
        }
        np.random.seed(seed)  # rliable's bootstrap draws from NumPy's global generator
        points, intervals = library.get_interval_estimates(
            scores, lambda matrix: np.array([metrics.aggregate_iqm(matrix)]), reps=reps
        )
        for algo in algos:
            rows.append(
                dict(
                    algo=algo,
                    env=env_id,
                    n_runs=len(scores[algo]),
                    iqm=float(points[algo][0]),
                    low=float(intervals[algo][0, 0]),
                    high=float(intervals[algo][1, 0]),
                )
            )
    return pd.DataFrame(rows)


def plot_iqm(table: pd.DataFrame) -> Figure:
    """One horizontal bar per algorithm (IQM) with its confidence interval, one panel per env."""
    algos, envs = list(dict.fromkeys(table["algo"])), list(dict.fromkeys(table["env"]))
    colors = line_colors(algos)
    fig, axes = plt.subplots(1, len(envs), figsize=(4.2 * len(envs), 0.5 * len(algos) + 1.5), squeeze=False, sharey=True)
    for ax, env_id in zip(axes[0], envs, strict=True):
        rows = table[table["env"] == env_id].set_index("algo").loc[algos]
        errors = np.stack([rows["iqm"] - rows["low"], rows["high"] - rows["iqm"]])
        ax.barh([label(algo) for algo in algos], rows["iqm"], xerr=errors, color=[colors[algo] for algo in algos], alpha=0.8)
        ax.set(title=env_id, xlabel="final success rate (IQM, 95 % CI)", xlim=(0, 1.02))
        ax.grid(axis="x", alpha=0.3)
    axes[0, 0].invert_yaxis()  # first algorithm on top, as listed on the command line (once: the y axis is shared)
    fig.tight_layout()
    return fig


def save(fig: Figure, path: Path, formats: list[str]) -> list[Path]:
    """Write ``fig`` as ``path.<format>`` for every format and close it."""
    written = [path.with_suffix(f".{fmt}") for fmt in formats]
    for file, fmt in zip(written, formats, strict=True):
        write_atomically(file, partial(fig.savefig, format=fmt, dpi=150, bbox_inches="tight"))
    plt.close(fig)
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "-f", "--log-folder", nargs="+", default=[Path("logs")], type=Path, dest="log_folders",
        help="the zoo's log folders (train -f); an algorithm's runs on an env in all of them are its seeds",
    )  # fmt: skip
    parser.add_argument("--algos", nargs="+", required=True, help="zoo algorithm names, one line (or bar) each")
    parser.add_argument("--envs", nargs="+", required=True, help="env ids, one panel each")
    parser.add_argument("--out", default="figures", type=Path, help="output folder")
    parser.add_argument("--format", nargs="+", default=["png", "pdf"], dest="formats", help="figure file formats")
    parser.add_argument("--window", default=100, type=int, help="episodes to smooth monitor-based success over")
    parser.add_argument("--iqm", action="store_true", help="also plot the IQM of the final success (rliable)")
    parser.add_argument("--reps", default=2000, type=int, help="bootstrap samples of the IQM confidence intervals")
    parser.add_argument(
        "--benchmark-csv",
        type=Path,
        nargs="+",
        help="draw only the hierarchical metrics, from benchmark.py CSVs instead of run folders",
    )
    parser.add_argument(
        "--legend",
        nargs="+",
        default=[],
        metavar="NAME=TEXT",
        help="legend text of an --algos name (e.g. dipper-pnh-goal0.2='DIPPER, policy alone'); default: its algorithm",
    )
    args = parser.parse_args()
    legend = dict(item.partition("=")[::2] for item in args.legend)
    unknown = sorted(set(legend) - set(args.algos))
    if unknown or any("=" not in item for item in args.legend):
        parser.error(f"--legend takes NAME=TEXT with NAME one of --algos, got {args.legend}")

    if args.benchmark_csv is not None:
        figure = draw_hierarchical_metrics(
            benchmark_csv_curves(*args.benchmark_csv), args.algos, args.envs, lambda name: legend.get(name) or label(name)
        )
        if figure is None:
            csvs = ", ".join(map(str, args.benchmark_csv))
            parser.exit(1, f"error: {csvs} have no subgoal distance or lower value for these runs\n")
        for path in save(figure, args.out / "hierarchical_metrics", args.formats):
            print(path)
        return

    try:
        written = save(plot_success(args.log_folders, args.algos, args.envs, args.window), args.out / "success", args.formats)
        metrics_fig = plot_hierarchical_metrics(args.log_folders, args.algos, args.envs)
        if metrics_fig is None:
            print("No progress.csv with rollout/subgoal_distance or rollout/low_value: no hierarchical-metrics figure.")
        else:
            written += save(metrics_fig, args.out / "hierarchical_metrics", args.formats)
        if args.iqm:
            table = final_success_iqm(args.log_folders, args.algos, args.envs, args.window, args.reps)
            written += save(plot_iqm(table), args.out / "final_success_iqm", args.formats)
            write_bytes_atomically(args.out / "final_success_iqm.csv", table.to_csv(index=False).encode())
            written.append(args.out / "final_success_iqm.csv")
    except FileNotFoundError as error:
        parser.exit(1, f"error: {error}\n")
    for path in written:
        print(path)


if __name__ == "__main__":
    main()
