"""``benchmark.py learning``'s report and the BENCHMARKS.md sections of every benchmark.

The report reads the runs on disk through ``plot.py``'s loaders: a table per task, the CSV ``<out>/<name>.csv`` with one
row per seed and evaluation, and a figure with a panel per task; :func:`write_section` puts a section, stamped with
its command, machine and date, into BENCHMARKS.md.
"""

from __future__ import annotations

import csv
import datetime
import os
import platform
import shlex
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import plot
import torch as th
from plot import label

from sb3_dipper.common.files import write_bytes_atomically

from .run import finished, run_steps_per_second, seed_folder

REPO = Path(__file__).resolve().parents[2]
BENCHMARKS_MD = REPO / "BENCHMARKS.md"
RESULTS_DIR = REPO / "docs" / "benchmarks"
# Logged by the option layer of hierarchical algorithms (``rollout/<key>`` in progress.csv); read at each evaluation.
OPTION_METRICS = ("subgoal_distance", "low_value")
# The labelled pairs in the preference dataset (DIPPER, PIPER: ``train/high_preference_pairs``): what a person would
# have labelled to get the result, had a person given the labels.
PREFERENCE_PAIRS = "preference_pairs"
PREFERENCE_PAIRS_KEY = "train/high_preference_pairs"
# The training episodes' success over the last 100 episodes, from the monitor files: the authors' "train success rate".
TRAINING_SUCCESS = "train_success"
CSV_METRICS = (*OPTION_METRICS, TRAINING_SUCCESS, PREFERENCE_PAIRS)
# The report's CSV: a row per run and evaluation; ``finished`` is 1 once the run had trained its whole budget, and
# ``steps_per_second`` is then the whole run's primitive steps per second of wall time (evaluations included), the same
# in each of its rows; CSVs written before it was recorded lack the column.
SPEED = "steps_per_second"
CSV_COLUMNS = ("env", "algo", "seed", "timesteps", "success", *CSV_METRICS, "finished", SPEED)


def machine() -> str:
    return f"{os.cpu_count()} cores, {platform.processor() or platform.machine()}, torch {th.__version__}, no GPU"


def command_line(script: str, arguments: list[str]) -> str:
    """The shell command that runs ``zoo_scripts/<script>`` with ``arguments``, each quoted where a shell would split or
    read it (``--set "preference_source='progress'"``), so a stamped command reruns as it ran."""
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


@dataclass
class SeedCurve:
    """Every evaluation of one seed's run."""

    seed: int
    finished: bool  # the run has ended (result.json); a running or cut-off run is partial
    steps: np.ndarray  # (evaluations,) primitive steps
    success: np.ndarray  # (evaluations,) success rates
    metrics: dict[str, np.ndarray]  # every CSV_METRICS key, (evaluations,), NaN where not logged
    steps_per_second: float | None = None  # the finished run's, wall time with evaluations; None if not recorded


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

    The option metrics at an evaluation are the last values ``progress.csv`` logged at or before its step. A damaged
    evaluation record of an unfinished run (killed while SB3's EvalCallback rewrote it in place) is left out with a
    warning, as a run not evaluated yet, so that one such run does not stop the report of the others; a finished run's
    is an error.
    """
    try:
        curve = plot.evaluation_curve(run)
    except ValueError as error:
        if finished(run):
            raise
        warnings.warn(f"{error} The run is unfinished: it is reported as not evaluated yet.")
        return None
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
    speed = run_steps_per_second(run)
    return SeedCurve(seed=seed, finished=finished(run), steps=steps, success=success, metrics=metrics, steps_per_second=speed)


def read_report_csv(path: Path) -> dict[tuple[str, str, int], SeedCurve]:
    """The runs of a CSV that :func:`report` wrote, by ``(env, name, seed)``: runs whose folders are gone (an earlier
    machine that no longer exists, another machine) still count in a later report (``--previous-csv``).

    :raises ValueError: the file lacks a column :func:`report` writes (names the file and the columns)
    """
    with open(path, newline="") as file:
        reader = csv.DictReader(file)
        missing = [column for column in CSV_COLUMNS if column != SPEED and column not in (reader.fieldnames or [])]
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
            steps_per_second=float(seed_rows[-1][SPEED]) if seed_rows[-1].get(SPEED) else None,
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


def run_speed(curves: Curves) -> str:
    """Mean primitive steps per second of wall time over the finished runs that recorded it, or a dash."""
    speeds = [seed.steps_per_second for seed in curves.per_seed if seed.steps_per_second is not None]
    if not speeds:
        return "-"
    return f"{np.mean(speeds):.0f}" + (
        f" ({len(speeds)} of {len(curves.per_seed)} seeds)" if len(speeds) < len(curves.per_seed) else ""
    )


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
                speed = "" if seed_curve.steps_per_second is None else f"{seed_curve.steps_per_second:.1f}"
                csv_rows.append(
                    f"{env_id},{name},{seed_curve.seed},{int(step)},{success:.4f},{values},{int(seed_curve.finished)},{speed}"
                )
        final = run_curves.success[:, -1]
        reached = np.flatnonzero(run_curves.success.mean(axis=0) >= 0.5)
        to_half = f"{int(run_curves.steps[reached[0]]):,}" if reached.size else "not reached"
        unfinished = run_curves.finished.count(False)
        runs = f"{len(run_curves.seeds)}" + (f" ({unfinished} partial)" if unfinished else "")
        rows.append(
            f"| {label(name)} | {runs} | {int(run_curves.steps[-1]):,} | {final.mean():.2f} +- {final.std():.2f} | "
            f"{final_mean(run_curves, TRAINING_SUCCESS)} | {to_half} | {final_mean(run_curves, 'subgoal_distance')} | "
            f"{final_mean(run_curves, 'low_value')} | {final_mean(run_curves, PREFERENCE_PAIRS, ',.0f')} | "
            f"{run_speed(run_curves)} |"
        )
    if not rows:
        return "No runs yet.", curves, csv_rows
    table = (
        "| algorithm | seeds | last evaluation (steps) | success there (mean +- std) | training success there (last 100 "
        "episodes) | steps to 50 % (mean curve) | subgoal distance there | lower value there | labelled pairs there | "
        "steps/s (finished runs, wall time) |\n"
        "|---|---|---|---|---|---|---|---|---|---|\n"
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
