"""What the higher level learns from, over training: the preference labels' ties and agreement with the true progress,
the DPO loss and accuracies, the likelihood of preferred and rejected steps, beside the success rate. A table and a
figure of several configurations, each with its seeds.

    python zoo_scripts/research/higher_level_diagnostics.py --runs dipper=logs/dipper/FetchPickAndPlaceFixed-v0_1 \
        --csv diagnostics.csv
    python zoo_scripts/research/higher_level_diagnostics.py --runs "lambda=1=runs/f42/lambda1" \
        "lambda=0.01=runs/f42/lambda0.01" --env FetchPickAndPlaceFixed-v0 --csv diagnostics.csv --plot diagnostics.png
    python zoo_scripts/research/higher_level_diagnostics.py --csv-in docs/benchmarks/diagnostics.csv --plot diagnostics.png

Each ``--runs LABEL=FOLDER`` (split at the last ``=``, so a label may hold one) names a configuration and its runs:
FOLDER is one zoo run folder (``logs/<algo>/<env>_<n>``) or a variant folder of ``benchmark.py learning``
(``<out>/<variant>``, whose runs are ``seed_<n>/<algo>/<env>_<k>``; ``--algo`` picks one algorithm where it holds
several). A run's seed is the ``seed_<n>`` its path goes through, else 0.

DIPPER logs the diagnostics to ``progress.csv`` (the zoo's ``CSVProgressCallback``; a resumed run's logs are read in
step order), PIPER and DPO-FLAT some of them. At each of a run's evaluations (``evaluations.npz``) the table takes the
success rate and, of each diagnostic, the last value logged at or before that step; a diagnostic never logged is
empty. ``--csv`` writes it, one row per env, configuration, seed and evaluation; ``--csv-in`` reads such tables back
(runs of another machine), alone or beside ``--runs``, so a figure regenerates from committed files. ``--plot`` draws a
panel per diagnostic with data: per configuration the mean over seeds with a band of one standard deviation, seeds that
went further as dotted lines (``plot.draw_seeds``); ``--env`` picks the env where the inputs hold several. The summary
printed is each configuration's mean over seeds at the last evaluation every one of its seeds reached.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import numpy as np
import pandas as pd

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.figure import Figure

from sb3_dipper.common.files import write_bytes_atomically

# Run as a script, this file's folder is on the path; the scripts' folder above it holds the modules it shares.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import plot

SHARE = (0.0, 1.0)


@dataclass(frozen=True)
class Diagnostic:
    """One diagnostic: a column of the table and a panel of the figure.

    :param column: the table's column
    :param keys: the ``progress.csv`` keys that log it, the first a run has is read (DIPPER's, then DPO-FLAT's)
    :param title: the panel's title
    :param limits: the range of a share or an accuracy, which the panel's band does not leave
    """

    column: str
    keys: tuple[str, ...]
    title: str
    limits: tuple[float, float] | None = None


DIAGNOSTICS = (
    Diagnostic("tie_share", ("train/high_tie_share", "train/tie_share"), "ties among trained pairs", SHARE),
    Diagnostic("new_tie_share", ("train/high_new_tie_share",), "ties among new labels", SHARE),
    Diagnostic("label_progress_agreement", ("train/high_label_progress_agreement",), "labels agreeing with progress", SHARE),
    Diagnostic("dpo_loss", ("train/high_dpo_loss", "train/dpo_loss"), "DPO loss on trained pairs"),
    Diagnostic("train_accuracy", ("train/high_pref_accuracy", "train/pref_accuracy"), "accuracy on trained pairs", SHARE),
    Diagnostic("heldout_accuracy", ("train/high_new_pair_accuracy",), "held-out pair accuracy", SHARE),
    Diagnostic("logp_preferred", ("train/high_new_logp_preferred",), "log-likelihood of preferred steps"),
    Diagnostic("logp_rejected", ("train/high_new_logp_rejected",), "log-likelihood of rejected steps"),
    Diagnostic("value_gap", ("train/high_value_gap",), "lower value gap (old minus current critic)"),
    Diagnostic("subgoal_distance", ("rollout/subgoal_distance",), plot.HIERARCHICAL_METRICS["rollout/subgoal_distance"]),
    Diagnostic("low_value", ("rollout/low_value",), plot.HIERARCHICAL_METRICS["rollout/low_value"]),
    Diagnostic("planned_share", ("rollout/planned_share",), "subgoals the planner proposed", SHARE),
    Diagnostic("goal_episode_success", ("rollout/goal_episode_success",), "training success, goal-driven episodes", SHARE),
    Diagnostic("policy_episode_success", ("rollout/policy_episode_success",), "training success, policy's episodes", SHARE),
    Diagnostic("new_start_gap", ("train/high_new_start_gap",), "how far apart new pairs started"),
)
# Diagnostics added after tables were committed: a table written before lacks their columns, read as never logged.
ADDED_LATER = ("goal_episode_success", "policy_episode_success", "new_start_gap")
KEY_COLUMNS = ("env", "config", "seed", "timesteps")
COLUMNS = (*KEY_COLUMNS, "success", *(diagnostic.column for diagnostic in DIAGNOSTICS))
# The zoo's run folder: <env_id>_<n>, with rl-zoo3's --uuid a uuid4 after it.
RUN_NAME = re.compile(r"(?P<env>.+?)_(?P<number>\d+)(_[0-9a-f-]{36})?")
SEED_FOLDER = re.compile(r"seed_(\d+)")


@dataclass(frozen=True)
class Run:
    """A zoo run folder with the env it trained on and the seed it counts as."""

    path: Path
    env_id: str
    seed: int


def warn(message: str) -> None:
    """``message`` on stderr: something the table leaves out or leaves empty."""
    print(f"warning: {message}", file=sys.stderr)


def parse_runs(items: Sequence[str]) -> dict[str, Path]:
    """The configurations of ``--runs``: ``LABEL=FOLDER`` split at the last ``=``, each label once.

    :raises ValueError: an item without ``=`` or a label, or a label given twice (names it)
    """
    configs: dict[str, Path] = {}
    for item in items:
        label, separator, folder = item.rpartition("=")
        if not separator or not label or not folder:
            raise ValueError(f"--runs takes LABEL=FOLDER, got {item!r}")
        if label in configs:
            raise ValueError(f"--runs names the label {label!r} twice ({configs[label]} and {folder}): give each its own")
        configs[label] = Path(folder)
    return configs


def run_seed(path: Path) -> int:
    """The seed of a run: the ``seed_<n>`` folder its path goes through nearest to it, else 0."""
    for part in reversed(path.parts):
        if match := SEED_FOLDER.fullmatch(part):
            return int(match[1])
    return 0


def is_run(folder: Path) -> bool:
    """Whether ``folder`` is a zoo run folder (it holds its evaluations or its SB3 log)."""
    return (folder / "evaluations.npz").is_file() or (folder / "progress.csv").is_file()


def find_runs(folder: Path, algo: str | None = None) -> list[Run]:
    """The runs of ``folder``: itself if it is a run folder, else those of a ``benchmark.py learning`` variant folder
    (``seed_<n>/<algo>/<env>_<k>``, of ``algo`` if given); of several runs of one seed on one env, the last.

    :raises FileNotFoundError: ``folder`` holds no run (names it)
    :raises ValueError: it holds runs of several algorithms and ``algo`` picks none
    """
    if is_run(folder):
        match = RUN_NAME.fullmatch(folder.name)
        return [Run(folder, match["env"] if match else folder.name, run_seed(folder))]
    numbered = []
    for path in folder.glob("seed_*/*/*"):
        match = RUN_NAME.fullmatch(path.name)
        if path.is_dir() and match and SEED_FOLDER.fullmatch(path.parents[1].name) and algo in (None, path.parent.name):
            numbered.append((run_seed(path), path.parent.name, match["env"], int(match["number"]), path))
    if not numbered:
        raise FileNotFoundError(
            f"{folder}: no zoo run in it (a run folder holds evaluations.npz or progress.csv; a variant folder of "
            "benchmark.py learning holds seed_<n>/<algo>/<env>_<k>/)" + ("" if algo is None else f", none of {algo}")
        )
    algos = sorted({algo_name for _, algo_name, *_ in numbered})
    if len(algos) > 1:
        raise ValueError(f"{folder} holds runs of several algorithms ({', '.join(algos)}): pick one with --algo")
    runs: dict[tuple[int, str], Run] = {}
    for seed, _, env_id, _, path in sorted(numbered):
        if (seed, env_id) in runs:
            warn(f"{folder}: seed {seed} has several runs on {env_id}; reading the last, {path.name}")
        runs[seed, env_id] = Run(path, env_id, seed)
    return list(runs.values())


def run_rows(run: Run, config: str) -> list[dict[str, object]]:
    """The table's rows of one run, one per evaluation: its success and, of each diagnostic, the last value logged at
    or before the evaluation's step (NaN where never logged by then).

    :raises FileNotFoundError: the run has no ``progress.csv`` (names it)
    """
    log = plot.load_progress(run.path)
    if log is None:
        raise FileNotFoundError(
            f"{run.path}: no progress.csv with {plot.STEPS_KEY} in it (the zoo writes one where the YAML entry's callback "
            "is sb3_dipper.zoo.CSVProgressCallback)"
        )
    evaluations = plot.evaluation_curve(run.path)
    if evaluations is None:
        warn(f"{run.path}: no evaluation yet (evaluations.npz with successes); left out")
        return []
    curves = {diagnostic.column: logged_curve(log, diagnostic) for diagnostic in DIAGNOSTICS}
    if all(curve is None for curve in curves.values()):
        warn(f"{run.path}: its progress.csv logs none of the diagnostics; their columns are empty")
    steps, success = evaluations
    return [
        dict(
            env=run.env_id,
            config=config,
            seed=run.seed,
            timesteps=int(step),
            success=float(step_success),
            **{column: plot.value_at(curve, step) for column, curve in curves.items()},
        )
        for step, step_success in zip(steps, success, strict=True)
    ]


def logged_curve(log: pd.DataFrame, diagnostic: Diagnostic) -> plot.Curve | None:
    """The diagnostic against steps under the first of its keys the log has, or None."""
    for key in diagnostic.keys:
        curve = plot.metric_curve(log, key)
        if curve is not None:
            return curve
    return None


def as_table(rows: Sequence[dict[str, object]]) -> pd.DataFrame:
    """Rows as the table: :data:`COLUMNS` in order, integer seeds and steps, floats elsewhere."""
    table = pd.DataFrame(list(rows), columns=list(COLUMNS))
    table[["env", "config"]] = table[["env", "config"]].astype(str)
    table[["seed", "timesteps"]] = table[["seed", "timesteps"]].astype(int)
    values = list(COLUMNS[len(KEY_COLUMNS) :])
    table[values] = table[values].astype(float)
    return table


def read_table(path: Path) -> pd.DataFrame:
    """A table this tool wrote with ``--csv``.

    A diagnostic of :data:`ADDED_LATER` that a table written before it lacks is empty, as a diagnostic never logged.

    :raises ValueError: the file is missing, empty, lacks a column or holds a value that is no number (names it)
    """
    try:
        # Only empty cells are missing values: a label such as "NA" stays a label.
        table = pd.read_csv(path, dtype={"env": str, "config": str}, keep_default_na=False, na_values=[""])
    except (OSError, pd.errors.EmptyDataError, pd.errors.ParserError) as error:
        raise ValueError(f"--csv-in {path}: not a readable CSV ({error})") from error
    for column in ADDED_LATER:
        if column not in table.columns:
            table[column] = np.nan
    missing = [column for column in COLUMNS if column not in table.columns]
    if missing:
        raise ValueError(
            f"--csv-in {path} lacks the columns {missing}: pass a CSV that higher_level_diagnostics.py --csv wrote "
            f"({','.join(COLUMNS)})"
        )
    try:
        return as_table(table[list(COLUMNS)].to_dict("records"))
    except (ValueError, TypeError) as error:
        raise ValueError(f"--csv-in {path}: a value is not a number ({error})") from error


def write_table(table: pd.DataFrame, path: Path) -> None:
    """The table as a CSV at ``path``, written whole or not at all; empty cells where a diagnostic was not logged."""
    write_bytes_atomically(path, table.to_csv(index=False, float_format="%.6g").encode())


def combine(sources: Sequence[tuple[str, pd.DataFrame]]) -> pd.DataFrame:
    """The tables of every source (a CSV or a ``LABEL=FOLDER``) as one.

    :raises ValueError: two sources both hold a seed of one configuration on one env (names them)
    """
    origin: dict[tuple[str, str, int], str] = {}
    for name, table in sources:
        for env_id, config, seed in table[["env", "config", "seed"]].drop_duplicates().itertuples(index=False):
            if (env_id, config, seed) in origin:
                raise ValueError(
                    f"seed {seed} of {config!r} on {env_id} comes from both {origin[env_id, config, seed]} and {name}"
                )
            origin[env_id, config, seed] = name
    return as_table([row for _, table in sources for row in table.to_dict("records")])


def seed_curves(table: pd.DataFrame, column: str) -> list[plot.Curve]:
    """Each seed's logged values of ``column`` against steps (the rows where it is not empty), seeds without any left
    out."""
    curves = []
    for _, seed_rows in table.groupby("seed"):
        logged = seed_rows.dropna(subset=[column]).sort_values("timesteps")
        if not logged.empty:
            curves.append((logged["timesteps"].to_numpy(dtype=float), logged[column].to_numpy(dtype=float)))
    return curves


def final_means(table: pd.DataFrame) -> pd.DataFrame:
    """Per configuration (a column): its seeds, the last evaluation every seed reached and, at that step, the mean over
    seeds of the success and of each diagnostic (the last value logged by then; "-" where none was)."""
    summary: dict[str, dict[str, str]] = {}
    for config, rows in table.groupby("config", sort=False):
        step = rows.groupby("seed")["timesteps"].max().min()
        column = {"seeds": ", ".join(map(str, sorted(rows["seed"].unique()))), "steps": plot.steps_label(step)}
        for name in COLUMNS[len(KEY_COLUMNS) :]:
            values = [plot.value_at(curve, step) for curve in seed_curves(rows, name)]
            logged = [value for value in values if not np.isnan(value)]
            column[name] = f"{np.mean(logged):.3f}" if logged else "-"
        summary[str(config)] = column
    return pd.DataFrame(summary)


def draw(table: pd.DataFrame, env_id: str) -> Figure | None:
    """One panel per diagnostic with data (four to a row), one line per configuration: the mean over its seeds with a
    band of one standard deviation (:func:`plot.draw_seeds`); None when no diagnostic has data."""
    diagnostics = [diagnostic for diagnostic in DIAGNOSTICS if table[diagnostic.column].notna().any()]
    if not diagnostics:
        return None
    configs = list(dict.fromkeys(table["config"]))
    colors = plot.line_colors(configs)
    columns = min(len(diagnostics), 4)
    rows = -(-len(diagnostics) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 3.2 * rows), squeeze=False)
    for ax, diagnostic in zip(axes.flat, diagnostics, strict=False):
        for config in configs:
            curves = seed_curves(table[table["config"] == config], diagnostic.column)
            if curves:
                plot.draw_seeds(ax, curves, colors[config], config, diagnostic.limits)
        ax.set_title(diagnostic.title)
        plot.steps_axis(ax)
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(diagnostics) :]:
        ax.set_axis_off()
    fig.suptitle(f"{env_id}: the higher level's diagnostics (mean and std over seeds; dotted: a seed past the others)")
    plot.shared_legend(fig, axes)
    return fig


def load(args: argparse.Namespace) -> pd.DataFrame:
    """The table of every ``--runs`` configuration and ``--csv-in`` file, restricted to ``--env`` if given.

    :raises ValueError, FileNotFoundError: an input the tool cannot read, or no rows of ``--env``
    """
    sources = [(str(path), read_table(path)) for path in args.csv_in or []]
    for config, folder in parse_runs(args.runs or []).items():
        rows = [row for run in find_runs(folder, args.algo) for row in run_rows(run, config)]
        sources.append((f"{config}={folder}", as_table(rows)))
    table = combine(sources)
    envs = list(dict.fromkeys(table["env"]))
    if args.env is not None:
        if args.env not in envs:
            raise ValueError(f"--env {args.env}: no evaluation of it in the inputs (they hold {envs or 'none'})")
        table = table[table["env"] == args.env].reset_index(drop=True)
    if table.empty:
        raise ValueError("no run of the inputs has an evaluation yet: nothing to tabulate")
    return table


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--runs", nargs="+", metavar="LABEL=FOLDER", help="a configuration's label and its run folder or variant folder"
    )
    parser.add_argument("--csv-in", nargs="+", type=Path, metavar="FILE", help="tables this tool wrote, read back")
    parser.add_argument("--csv", type=Path, help="write the table (a row per env, configuration, seed and evaluation)")
    parser.add_argument("--plot", type=Path, help="draw the figure to this file (its suffix is the format, e.g. .png)")
    parser.add_argument("--env", help="the env to tabulate and plot (needed for --plot when the inputs hold several)")
    parser.add_argument("--algo", help="the algorithm folder to read in variant folders that hold several")
    args = parser.parse_args(argv)
    if not args.runs and not args.csv_in:
        parser.error("give --runs LABEL=FOLDER ..., --csv-in FILE ..., or both")
    try:
        table = load(args)
    except (ValueError, FileNotFoundError) as error:
        parser.error(str(error))
    envs = list(dict.fromkeys(table["env"]))
    if args.plot is not None and len(envs) > 1:
        parser.error(f"the inputs hold several envs ({', '.join(envs)}): pick the one to plot with --env")
    for env_id, rows in table.groupby("env", sort=False):
        print(f"{env_id}: mean over seeds at the last evaluation every seed of a configuration reached")
        print(final_means(rows).to_string(), end="\n\n")
    if args.csv is not None:
        write_table(table, args.csv)
        print(args.csv)
    if args.plot is not None:
        figure = draw(table, envs[0])
        if figure is None:
            parser.exit(1, f"error: no diagnostic was logged on {envs[0]}: no figure\n")
        for path in plot.save(figure, args.plot, [args.plot.suffix.removeprefix(".") or "png"]):
            print(path)


if __name__ == "__main__":
    main()
