"""The results matrix of the paper's tasks, from the committed CSVs: one command regenerates it everywhere it is shown.

    python zoo_scripts/report.py                # print the matrix
    python zoo_scripts/report.py --write        # and put it into BENCHMARKS.md and README.md, with its CSV and figure

Each cell is the deterministic success at each seed's last evaluation within the task's budget, the mean +- std over
the seeds, and the number of seeds in brackets (a ``*`` marks a seed that had not finished its budget). A cell names
exactly one configuration: the run label of ``docs/benchmarks/paper-tasks-cpu.csv`` (``<algo>`` or
``<algo>-<variant>``, see :data:`COLUMNS`) or, for the evaluations of a final model with part of it switched off
(``zoo_scripts/research/planner_share.py``), a case of a planner-share CSV. The columns say who acts:

* the ``dipper`` profile as trained, at its last evaluation in training (no paper-task profile plans at evaluation:
  their ``planner_kwargs`` leave ``in_predict`` off, so the preference-trained policy proposes every subgoal);
* its final models evaluated again with the planner off (the same policy, other episodes), with the higher policy
  reset to untrained weights, and with the goal handed to the lower level as every subgoal (what the hierarchy adds is
  measured against these controls);
* the lower level driven by the planner, the goal wherever its graph knew no path: every earlier ``dipper`` run with
  ``planning="subgoal"``, whose planner marked every row as planned, so the preference-trained policy never acted;
* the paper's DIPPER and the baselines.

The task column names what every method that takes demonstrations learns from at the CPU profiles (the DART episodes
where DIPPER's profile takes them).

The matrix is written between ``<!-- results-matrix -->`` markers, the figure (one panel per task, one curve per column
that has learning curves: the mean over seeds and a band of one standard deviation) to
``docs/benchmarks/paper-tasks.png`` and the cells to ``docs/benchmarks/paper-tasks-matrix.csv``. The paper's ablations
of lambda and beta on the fixed pick-and-place (``docs/benchmarks/ablations-pnp-fixed.csv``, the paper's values from the
``dipper_paper`` rows) go between ``<!-- ablations -->`` markers of ``BENCHMARKS.md``, their figure (one panel per
parameter) to ``docs/benchmarks/ablations-pnp-fixed.png``. How many of each seed's evaluations succeeded on the fixed
pick-and-place, per column, goes between ``<!-- evaluations-with-success -->`` markers of ``BENCHMARKS.md``.
"""

from __future__ import annotations

import argparse
import csv
import io
import re
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import plot

from sb3_dipper.common.files import write_bytes_atomically
from sb3_dipper.zoo.run_config import load_entry

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "docs" / "benchmarks"
LEARNING_CSV = RESULTS / "paper-tasks-cpu.csv"

TASKS = {  # task: (budget in primitive steps, short name)
    "FetchPickAndPlaceFixed-v0": (150_000, "fixed pick-and-place"),
    "FetchPushFixed-v0": (640_000, "fixed push"),
    "FetchPickAndPlace-v4": (150_000, "random pick-and-place"),
    "FetchPush-v4": (640_000, "random push"),
    "FrankaKitchenMicrowaveBurner-v0": (675_000, "kitchen"),
    "FetchFourRoomMazeFixed-v0": (700_000, "fixed Fetch maze"),
    "FetchFourRoomMaze-v0": (700_000, "random Fetch mazes"),
}
PNP_FIXED, PUSH_FIXED, PNP, PUSH, KITCHEN, MAZE_FIXED, MAZE = TASKS


def profile_demonstrations(task: str) -> str:
    """What the ``dipper`` profile of ``task`` learns from (``demo_kwargs`` of hyperparams/dipper.yml), which every CPU
    profile that takes demonstrations shares."""
    demo_path = (load_entry("dipper", task).get("demo_kwargs") or {}).get("demo_path")
    if demo_path is None:
        return "no demonstrations"
    if demo_path == "auto":
        return "1 demonstration"
    return f"{demo_path.removeprefix('auto:dart')} DART episodes"


@dataclass(frozen=True)
class Learning:
    """Final evaluations of the runs labelled ``label`` in a learning-curve CSV; where there are none yet, those of
    ``earlier``, the same method's runs at its earlier profile (the cell is then marked: :data:`EARLIER_PROFILE_LEGEND`)."""

    label: str
    csv: str = "paper-tasks-cpu.csv"
    earlier: str | None = None


@dataclass(frozen=True)
class Evaluated:
    """Success of final models evaluated as ``case`` in a planner-share CSV, the runs whose path contains ``run``."""

    csv: str
    run: str
    case: str


Source = Learning | Evaluated

# The DIPPER profile of hyperparams/dipper.yml on each task, and the runs of its controls.
DIPPER_PROFILE: dict[str, Source] = {
    PNP_FIXED: Learning("dipper-goal-episodes"),
    PUSH_FIXED: Learning("dipper-goal-episodes"),
    PNP: Learning("dipper-anchored-goalep-hgp0"),
    PUSH: Learning("dipper-anchored-goalep-hgp0"),
    KITCHEN: Learning("dipper-dart20-noqf-bc1-demonorm-demo0.5"),
    MAZE_FIXED: Learning("dipper-goal-episodes"),
    MAZE: Learning("dipper-anchored-goalep"),
}


def final_models(case: str) -> dict[str, Source]:
    """The final models of the ``dipper`` profile's runs evaluated as ``case`` (``zoo_scripts/research/planner_share.py``)."""
    sources: dict[str, Source] = {
        PNP_FIXED: Evaluated("planner-share-goal-episodes-profile.csv", "FetchPickAndPlaceFixed", case),
        PUSH_FIXED: Evaluated("planner-share-goal-episodes-push.csv", "FetchPushFixed", case),
        PNP: Evaluated("planner-share-anchored-goalep-hgp0.csv", "/anchored-goalep-hgp0/", case),
        PUSH: Evaluated("planner-share-anchored-goalep-push-hgp0.csv", "/anchored-goalep-hgp0/", case),
        MAZE_FIXED: Evaluated("planner-share-goal-episodes-maze.csv", "FetchFourRoomMazeFixed", case),
        MAZE: Evaluated("planner-share-anchored-goalep-rmaze.csv", "/anchored-goalep/", case),
    }
    # Without a planner the model as trained is its policy alone.
    kitchen_case = "as_trained" if case == "policy_alone" else case
    sources[KITCHEN] = Evaluated("planner-share-kitchen-demo0.5.csv", "dipper", kitchen_case)
    return sources


PLANNER_GOAL: dict[str, Source] = {
    PNP_FIXED: Learning("planner_goal-dipper-switches-bc0.02"),
    PUSH_FIXED: Learning("planner_goal-dipper-switches"),
    PNP: Learning("planner_goal-dipper-switches-dart20-noqf-bc1-demo0.5"),
    PUSH: Learning("planner_goal-dipper-switches-dart200-noqf-bc1-demo0.5"),
}


# The baselines' CPU profiles changed: their higher SAC (PIPER, HIER, HAC, SAGA) had SB3's entropy coefficient tuned
# from 1.0 and tau 0.005 where the authors' code has alpha 0.05 and polyak 0.8 per 10 batches (RAPS: tau only), and
# on the fixed pick-and-place every method but DIPPER's profile and SAC+HER+BC cloned at 0.0078 where those two clone
# at 0.02 (the authors' balance at this batch). The rows of the earlier profiles carry these suffixes; a cell shows
# them, marked, until the method is rerun at its profile.
EARLIER_PROFILE_MARK = "†"
EARLIER_PROFILE_LEGEND = (
    f"{EARLIER_PROFILE_MARK}: the method's earlier CPU profile, not yet rerun at its current one: its higher SAC at "
    "SB3's defaults (entropy coefficient tuned from 1.0, tau 0.005) where the authors' code has alpha 0.05 and polyak "
    "0.8 per 10 batches (RAPS: tau only), and on the fixed pick-and-place a cloning weight of 0.0078 where the other "
    "methods clone at 0.02 (the authors' balance at this batch)."
)
HIGHER_SAC_METHODS = ("piper", "hier", "hac", "saga")


def earlier_label(label: str, task: str) -> str | None:
    """The label the rows of ``label``'s earlier profile carry on ``task`` (``None``: its profile there is unchanged).

    ``<algo>[-<variant>]``: the higher-SAC methods insert ``highauto`` (RAPS ``hightau0.005``) after the algorithm,
    and on the fixed pick-and-place every method that clones its demonstration (but DIPPER's profile) ``bc0.0078``.
    """
    algo, _, variant = label.partition("-")
    suffixes = []
    if algo in HIGHER_SAC_METHODS:
        suffixes.append("highauto")
    elif algo == "raps":
        suffixes.append("hightau0.005")
    if task == PNP_FIXED and algo in (*HIGHER_SAC_METHODS, "dipper_paper", "dipper_nov"):
        suffixes.append("bc0.0078")
    if not suffixes:
        return None
    return "-".join([algo, *suffixes, *([variant] if variant else [])])


def everywhere(label: str, earlier: dict[str, str] | None = None) -> dict[str, Source]:
    """``label`` on every task, each with its earlier profile's runs (:func:`earlier_label`, or per task where
    ``earlier`` names them)."""
    return {task: Learning(label, earlier=(earlier or {}).get(task, earlier_label(label, task))) for task in TASKS}


# (heading, the source of each task's cell)
DIPPER_COLUMNS: list[tuple[str, dict[str, Source]]] = [
    ("DIPPER as trained", DIPPER_PROFILE),
    ("its policy alone", final_models("policy_alone")),
    ("policy untrained", final_models("untrained_policy")),
    ("goal as every subgoal", final_models("lower_level_alone")),
    ("planner + goal, earlier runs", PLANNER_GOAL),
    (
        "paper's DIPPER",
        everywhere("dipper_paper"),
    ),
]
HIERARCHICAL_COLUMNS: list[tuple[str, dict[str, Source]]] = [
    ("DIPPER-No-V", everywhere("dipper_nov")),
    (
        "HIER",
        everywhere(
            "hier",
            {  # the earlier profile's runs there were variants: the DART episodes the profile now clones
                PNP: "hier-highauto-dart20-noqf-bc1-demo0.5",
                PUSH: "hier-highauto-dart200-noqf-bc1-demo0.5",
                KITCHEN: "hier-highauto-dart20-noqf-bc1-demonorm-demo0.5",
            },
        ),
    ),
    ("HAC", everywhere("hac")),
    ("SAGA", everywhere("saga")),
    ("RAPS", everywhere("raps")),
    ("PIPER", everywhere("piper")),
]
FLAT_COLUMNS: list[tuple[str, dict[str, Source]]] = [
    ("DPO-FLAT", everywhere("dpo_flat")),
    ("DAC", everywhere("dac")),
    ("SAC+HER", everywhere("sac")),
    ("SAC+HER+BC", everywhere("sac_demo")),
]
# Whose success, for the hierarchical baselines: their final models as trained, with the higher policy untrained and
# with the goal as every subgoal (zoo_scripts/research/planner_share.py), per task and method: (csv, the runs' path part).
# A method marked with EARLIER_PROFILE_MARK is its earlier profile's runs.
BASELINE_FINAL_MODELS: list[tuple[str, str, str, str]] = [
    (PNP_FIXED, f"HAC{EARLIER_PROFILE_MARK}", "planner-share-baselines.csv", "/hac/"),
    (PNP_FIXED, f"SAGA{EARLIER_PROFILE_MARK}", "planner-share-baselines.csv", "/saga/"),
    (PNP_FIXED, f"PIPER{EARLIER_PROFILE_MARK}", "planner-share-baselines.csv", "/piper/"),
    (PNP_FIXED, f"DIPPER-No-V{EARLIER_PROFILE_MARK}", "planner-share-baselines.csv", "/dipper_nov/"),
    (PNP_FIXED, "PIPER", "planner-share-pnp-fixed-baselines.csv", "/piper/"),
    (PNP_FIXED, "HAC", "planner-share-pnp-fixed-baselines.csv", "/hac/"),
    (PNP_FIXED, "HIER", "planner-share-pnp-fixed-baselines.csv", "/hier/"),
    (PNP_FIXED, "SAGA", "planner-share-pnp-fixed-baselines.csv", "/saga/"),
    (PNP_FIXED, "DIPPER-No-V", "planner-share-pnp-fixed-baselines.csv", "/dipper_nov/"),
    (PNP_FIXED, "paper's DIPPER", "planner-share-pnp-fixed-baselines.csv", "/dipper_paper/"),
    (PUSH_FIXED, "DIPPER-No-V", "planner-share-nov-push.csv", "/dipper_nov/"),
    (PUSH_FIXED, f"HAC{EARLIER_PROFILE_MARK}", "planner-share-push-fixed-baselines.csv", "/hac/"),
    (PUSH_FIXED, f"SAGA{EARLIER_PROFILE_MARK}", "planner-share-push-fixed-baselines.csv", "/saga/"),
    (PNP, f"HAC{EARLIER_PROFILE_MARK}", "planner-share-pnp-random-baselines.csv", "/hac/"),
    (PNP, f"PIPER{EARLIER_PROFILE_MARK}", "planner-share-pnp-random-baselines.csv", "/piper/"),
    (PNP, "DIPPER-No-V", "planner-share-pnp-random-baselines.csv", "/dipper_nov/"),
    (PNP, f"SAGA{EARLIER_PROFILE_MARK}", "planner-share-pnp-random-baselines.csv", "/saga/"),
    (PNP, "paper's DIPPER", "planner-share-pnp-random-baselines.csv", "/dipper_paper/"),
    (PUSH, f"HIER{EARLIER_PROFILE_MARK}", "planner-share-push-random-dart200-hier.csv", "/hier/"),
    (PUSH, "paper's DIPPER", "planner-share-push-random-baselines.csv", "/dipper_paper/"),
    (KITCHEN, f"HIER{EARLIER_PROFILE_MARK}", "planner-share-kitchen-hier-demo0.5.csv", "/hier/"),
    (KITCHEN, "paper's DIPPER", "planner-share-kitchen-baselines.csv", "/dipper_paper/"),
    (MAZE_FIXED, f"HAC{EARLIER_PROFILE_MARK}", "planner-share-maze-baselines.csv", "/hac/"),
    (MAZE_FIXED, f"SAGA{EARLIER_PROFILE_MARK}", "planner-share-maze-baselines.csv", "/saga/"),
    (MAZE_FIXED, f"PIPER{EARLIER_PROFILE_MARK}", "planner-share-maze-baselines.csv", "/piper/"),
    (MAZE_FIXED, "DIPPER-No-V", "planner-share-maze-baselines.csv", "/dipper_nov/"),
    (MAZE_FIXED, f"HIER{EARLIER_PROFILE_MARK}", "planner-share-maze-baselines.csv", "/hier/"),
    (MAZE, f"HAC{EARLIER_PROFILE_MARK}", "planner-share-rmaze-baselines.csv", "/hac/"),
    (MAZE, f"SAGA{EARLIER_PROFILE_MARK}", "planner-share-rmaze-baselines.csv", "/saga/"),
    (MAZE, f"HIER{EARLIER_PROFILE_MARK}", "planner-share-rmaze-baselines.csv", "/hier/"),
    (MAZE, f"PIPER{EARLIER_PROFILE_MARK}", "planner-share-rmaze-baselines.csv", "/piper/"),
    (MAZE, "DIPPER-No-V", "planner-share-rmaze-baselines.csv", "/dipper_nov/"),
]
FINAL_MODEL_CASES = {
    "as_trained": "as trained",
    "untrained_policy": "higher policy untrained",
    "lower_level_alone": "goal as every subgoal",
}

ANCHORS = {  # PIPER's public figures (the authors' code), read off their curves: the paper's own anchors
    PNP_FIXED: "about 0.75 at 147k",
    PUSH_FIXED: "about 0.75 at 640k",
    KITCHEN: "about 0.45 at 675k",
    MAZE_FIXED: "about 0.55 at 700k",
}


ABLATIONS_CSV = "ablations-pnp-fixed.csv"
# The paper's ablations of its DIPPER on the fixed pick-and-place: (parameter, [(value, its runs)]), the rest the paper's.
ABLATIONS: list[tuple[str, list[tuple[str, Learning]]]] = [
    (
        "lambda",
        [
            ("0", Learning("dipper_paper-bc0.0078-lambda0", ABLATIONS_CSV)),
            ("0.01", Learning("dipper_paper-bc0.0078-lambda0.01", ABLATIONS_CSV)),
            ("0.1 (the paper's)", Learning("dipper_paper-bc0.0078")),
            ("1", Learning("dipper_paper-bc0.0078-lambda1", ABLATIONS_CSV)),
        ],
    ),
    (
        "beta",
        [
            ("0.01", Learning("dipper_paper-bc0.0078-beta0.01", ABLATIONS_CSV)),
            ("0.1 (the paper's)", Learning("dipper_paper-bc0.0078")),
            ("1", Learning("dipper_paper-bc0.0078-beta1", ABLATIONS_CSV)),
        ],
    ),
]


@dataclass
class Cell:
    success: list[float]  # one per seed
    partial: int  # seeds that had not finished their budget
    speeds: list[float] = field(default_factory=list)  # steps/s of wall time of the finished runs that recorded it
    label: str = ""  # the runs' label (a Learning source's, or its earlier profile's)
    earlier: bool = False  # made by the method's earlier profile

    def text(self) -> str:
        if not self.success:
            return ""
        values = np.array(self.success)
        partial = "*" if self.partial else ""
        mark = EARLIER_PROFILE_MARK if self.earlier else ""
        if len(values) == 1:
            return f"{values[0]:.2f} (1{partial}){mark}"
        return f"{values.mean():.2f} +- {values.std():.2f} ({len(values)}{partial}){mark}"


def learning_rows(name: str) -> dict[tuple[str, str], dict[int, list[dict[str, str]]]]:
    """The rows of a learning-curve CSV by (task, label) and seed."""
    rows: dict[tuple[str, str], dict[int, list[dict[str, str]]]] = defaultdict(lambda: defaultdict(list))
    with open(RESULTS / name, newline="") as file:
        for row in csv.DictReader(file):
            rows[(row["env"], row["algo"])][int(row["seed"])].append(row)
    return rows


def learning_cell(task: str, source: Learning) -> tuple[Cell, list[plot.Curve]]:
    """The final evaluation within the budget of each seed, and each seed's curve."""
    rows_by_label = learning_rows(source.csv)
    seeds = rows_by_label.get((task, source.label), {})
    cell, curves = Cell([], 0, label=source.label), []
    if not seeds and source.earlier is not None:
        seeds = rows_by_label.get((task, source.earlier), {})
        cell.label, cell.earlier = source.earlier, bool(seeds)
    budget = TASKS[task][0]
    for rows in seeds.values():
        within = [row for row in rows if int(row["timesteps"]) <= budget]
        if not within:
            continue
        cell.success.append(float(within[-1]["success"]))
        cell.partial += within[-1]["finished"] != "1"
        if rows[-1].get("steps_per_second"):
            cell.speeds.append(float(rows[-1]["steps_per_second"]))
        curves.append((np.array([float(r["timesteps"]) for r in within]), np.array([float(r["success"]) for r in within])))
    return cell, curves


def evaluated_cell(source: Evaluated) -> Cell:
    """The case's success of every final model of the matching runs (the largest ``steps`` of each run)."""
    path = RESULTS / source.csv
    if not path.is_file():
        return Cell([], 0)
    finals: dict[str, tuple[int, float]] = {}
    with open(path, newline="") as file:
        for row in csv.DictReader(file):
            if source.run in row["run"] and row["case"] == source.case:
                steps = int(row.get("steps") or 0)
                if row["run"] not in finals or steps >= finals[row["run"]][0]:
                    finals[row["run"]] = (steps, float(row["success"]))
    return Cell([success for _, success in finals.values()], 0)


def cell(task: str, source: Source | None) -> tuple[Cell, list[plot.Curve]]:
    if source is None:
        return Cell([], 0), []
    if isinstance(source, Learning):
        return learning_cell(task, source)
    return evaluated_cell(source), []


def matrix() -> tuple[str, list[list[str]], dict[str, dict[str, list[plot.Curve]]]]:
    """The three markdown tables (DIPPER and its controls, hierarchical baselines, flat baselines), the CSV rows and the
    figure's panels."""
    csv_rows = [["task", "column", "source", "seeds", "success", "steps_per_second", "speed_runs"]]
    panels: dict[str, dict[str, list[plot.Curve]]] = {task: {} for task in TASKS}
    demonstrations = {task: profile_demonstrations(task) for task in TASKS}
    tables = []
    for columns, extra in ((DIPPER_COLUMNS, None), (HIERARCHICAL_COLUMNS, None), (FLAT_COLUMNS, "anchor (PIPER's code)")):
        header = ["task (budget, demonstrations)", *(heading for heading, _ in columns), *([extra] if extra else [])]
        lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        for task, (budget, _) in TASKS.items():
            cells = []
            for heading, sources in columns:
                source = sources.get(task)
                value, curves = cell(task, source)
                cells.append(value.text())
                if curves:
                    panels[task][f"{heading} {EARLIER_PROFILE_MARK}" if value.earlier else heading] = curves
                if value.success:
                    where = value.label if isinstance(source, Learning) else f"{source.csv}:{source.case}"  # type: ignore[union-attr]
                    speed = f"{np.mean(value.speeds):.0f}" if value.speeds else ""
                    seeds = str(len(value.success))
                    csv_rows.append([task, heading, where, seeds, value.text(), speed, str(len(value.speeds))])
            anchor = [ANCHORS.get(task, "")] if extra else []
            lines.append(f"| `{task}` ({budget // 1000}k, {demonstrations[task]}) | " + " | ".join(cells + anchor) + " |")
        tables.append("\n".join(lines))
    legend = (
        "Methods without demonstrations: RAPS, DPO-FLAT, SAC+HER; DAC, which cannot learn without them, takes the task's "
        "one scripted demonstration where the others take none."
    )
    return "\n\n".join([*tables, legend, EARLIER_PROFILE_LEGEND]), csv_rows, panels


def cell_speeds(csv_rows: list[list[str]]) -> str:
    """The training speed of every cell that recorded it (the matrix CSV's rows): the table between
    ``<!-- cell-speed -->`` markers."""
    header = ["task", "column", "runs", "seeds recorded", "primitive steps/s (mean of runs)"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    by_task = sorted(csv_rows[1:], key=lambda row: list(TASKS).index(row[0]))
    for task, column, source, seeds, _, speed, recorded in by_task:
        if speed:
            lines.append(f"| `{task}` | {column} | `{source}` | {recorded} of {seeds} | {speed} |")
    return "\n".join(lines)


def whose_success() -> str:
    """The hierarchical baselines' final models, three ways: the table between ``<!-- whose-success -->`` markers."""
    header = ["task", "method", *FINAL_MODEL_CASES.values()]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for task, method, csv_name, run in BASELINE_FINAL_MODELS:
        cells = [evaluated_cell(Evaluated(csv_name, run, case)).text() for case in FINAL_MODEL_CASES]
        lines.append(f"| `{task}` | {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def success_counts(curves: list[plot.Curve]) -> list[str]:
    """Per seed's curve: how many of its evaluations had any success, as ``"k of n"``."""
    return [f"{int(np.sum(success > 0))} of {len(success)}" for _, success in curves]


def evaluations_with_success(panels: dict[str, dict[str, list[plot.Curve]]], task: str = PNP_FIXED) -> str:
    """Per column with learning curves on ``task`` (the figure's panel): how many of each seed's evaluations within the
    budget had any success, and of all of them; the table between ``<!-- evaluations-with-success -->`` markers. Where
    the start and the goal never move every evaluation is all or nothing, so a seed's last one, the matrix's cell, says
    little about how often it succeeds."""
    header = ["column", "evaluations with success, per seed", "of all"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for heading, curves in panels[task].items():
        succeeded = sum(int(np.sum(success > 0)) for _, success in curves)
        evaluations = sum(len(success) for _, success in curves)
        lines.append(f"| {heading} | {', '.join(success_counts(curves))} | {succeeded} of {evaluations} |")
    return "\n".join(lines)


def ablations() -> tuple[str, dict[str, dict[str, list[plot.Curve]]]]:
    """The ablation table (per value: success at the budget, evaluations with any success per seed, the mean success
    over every evaluation) and the figure's panels, one per parameter."""
    header = ["parameter", "value", "success at 150k", "evaluations with success, per seed", "mean over evaluations"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    panels: dict[str, dict[str, list[plot.Curve]]] = {}
    for parameter, settings in ABLATIONS:
        panel = panels.setdefault(f"{parameter}, {TASKS[PNP_FIXED][1]}", {})
        for value, source in settings:
            final, curves = learning_cell(PNP_FIXED, source)
            panel[f"{parameter} = {value}"] = curves
            counts = ", ".join(success_counts(curves))
            overall = f"{np.mean(np.concatenate([success for _, success in curves])):.2f}" if curves else ""
            lines.append(f"| {parameter} | {value} | {final.text()} | {counts} | {overall} |")
    return "\n".join(lines), panels


def write_between_markers(path: Path, text: str, name: str = "results-matrix") -> None:
    """Replace what lies between ``<!-- name -->`` and ``<!-- /name -->`` in ``path`` by ``text``."""
    marker = re.compile(rf"(<!-- {name} -->\n).*?(<!-- /{name} -->)", re.DOTALL)
    content = path.read_text()
    if not marker.search(content):
        raise SystemExit(f"{path} has no <!-- {name} --> ... <!-- /{name} --> markers to write between")
    write_bytes_atomically(path, marker.sub(lambda match: match[1] + text + "\n" + match[2], content).encode())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--write", action="store_true", help="write into BENCHMARKS.md, README.md and docs/benchmarks/")
    args = parser.parse_args()
    tables, csv_rows, panels = matrix()
    whose = whose_success()
    speeds = cell_speeds(csv_rows)
    ablation_table, ablation_panels = ablations()
    flips = evaluations_with_success(panels)
    print(tables, whose, speeds, flips, ablation_table, sep="\n\n")
    if args.write:
        for document in (REPO / "BENCHMARKS.md", REPO / "README.md"):
            write_between_markers(document, tables)
        write_between_markers(REPO / "BENCHMARKS.md", whose, "whose-success")
        write_between_markers(REPO / "BENCHMARKS.md", speeds, "cell-speed")
        write_between_markers(REPO / "BENCHMARKS.md", ablation_table, "ablations")
        write_between_markers(REPO / "BENCHMARKS.md", flips, "evaluations-with-success")
        lines = io.StringIO()
        csv.writer(lines, lineterminator="\n").writerows(csv_rows)
        write_bytes_atomically(RESULTS / "paper-tasks-matrix.csv", lines.getvalue().encode())
        figure = plot.draw_success({task: lines for task, lines in panels.items() if lines}, labels=str)
        plot.save(figure, RESULTS / "paper-tasks", ["png"])
        plot.save(plot.draw_success(ablation_panels, labels=str), RESULTS / "ablations-pnp-fixed", ["png"])


if __name__ == "__main__":
    main()
