"""Benchmarks: throughput ratios and learning curves; BENCHMARKS.md sections (command, machine, date) only on request.

    python zoo_scripts/benchmark.py throughput                      # DIPPER/HIER seconds per step vs SB3 SAC+HER
    python zoo_scripts/benchmark.py profiles --write                # steps/s at the paper tasks' CPU profiles
    python zoo_scripts/benchmark.py profiles --envs FetchPushFixed-v0 --fused-adam   # and with fused Adam optimizers
    python zoo_scripts/benchmark.py profiles --envs FetchPush-v4 --variant b128 batch_size=128   # and a cheaper copy
    python zoo_scripts/benchmark.py updates                         # ms per lower/higher update vs SB3's SAC update
    python zoo_scripts/benchmark.py learning --algos dipper hier sac --seeds 0 1 2 --workers 2
    python zoo_scripts/benchmark.py learning --algos dipper --variant no-nll --name ablations \
        --set "switch_kwargs=dict(hindsight_actions=True, truncate_at_goal=True)"   # the maze's switches but the NLL term
    python zoo_scripts/benchmark.py learning --protocol quick --out runs/quick            # every algorithm, <= 1 h
    python zoo_scripts/benchmark.py learning --protocol quick --out runs/quick --report-only --write   # BENCHMARKS.md
    python zoo_scripts/benchmark.py learning --protocol paper --ray-address HEAD:6379     # paper tasks on a cluster
    python zoo_scripts/benchmark.py learning --envs FetchPush-v4 FetchPickAndPlace-v4 --algos dipper sac --seeds 0 1

``learning`` runs every (algorithm, task, seed) triple as the RL-Zoo run a user would start::

    sb3-dipper-zoo train --algo ALGO --env ENV --seed SEED -f OUT/VARIANT/seed_SEED --eval-freq F --eval-episodes N \
        --n-eval-envs E --num-threads 1 [-n BUDGET] [--save-freq S] [--env-kwargs k:v ...] [-params k:v ...]

so hyperparameters come from the task's entry of ``hyperparams/<algo>.yml`` (``callback`` included) exactly as there,
``--set key=value`` and ``--env-kwargs key=value`` become the zoo's ``-params key:value`` and ``--env-kwargs key:value``
(the value is read as Python by rl-zoo3: quote strings, ``--set "preference_source='progress'"``; a dict replaces the
entry's whole dict, so ``--set "switch_kwargs=dict(...)"`` names every switch the runs keep on; the env kwargs apply to
the training and the evaluation envs), and each run is an ordinary zoo run folder::

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
leftover folders are removed first). Runs longer than one sitting are trained in parts: with ``--pause-after-minutes M``
each run pauses after M minutes of training with a resume checkpoint in its folder (``resume/``, see
``sb3-dipper-zoo train --pause-after-minutes``), and rerunning the command continues every paused run where it stopped,
in the same folder and on the same evaluation grid (``parts.json`` adds up the parts' time for ``result.json``).
``zoo_scripts/plot.py -f OUT/default/seed_*`` plots the runs like any zoo runs.
The report reads the runs on disk through ``plot.py``'s loaders (finished or not, ``--report-only`` without running
anything): a table per task (seeds, with the unfinished ones counted as partial, the last evaluation every seed has
reached, the success there as mean +- std over seeds, the steps where the mean success first reaches 50 %, and for
hierarchical algorithms the subgoal distance and lower value last logged at or before that step, for the
preference-trained ones the labelled pairs in their dataset then: what a person would have labelled, and the finished
runs' primitive steps per second of wall time, evaluations included), the CSV ``OUT/<name>.csv`` with one row per seed
and evaluation (``steps_per_second`` in every row of a finished run), and a figure with a panel per task
(``plot.draw_success``).
The tables are printed and the figure written to ``OUT/<name>.png``; only ``--write`` puts the section ``<name>`` into
BENCHMARKS.md (``--benchmarks-md``) and the figure and the CSV into docs/benchmarks/ (``--figures-dir``). Run folders
do not outlive the machine they ran on; the CSV does: with ``--previous-csv docs/benchmarks/<name>.csv`` a later report
takes every run it lists that has no folder in ``--out`` from it (its ``finished`` column keeps partial runs partial),
so a table grows across machines and sittings (the CSV's steps, success and metrics are the table's). rl-zoo3
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
import difflib
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

sys.path.insert(0, str(Path(__file__).resolve().parent))
import gymnasium as gym
import plot
from benchmarking.profile import (
    FUSED_ADAM,
    THROUGHPUT_LOWER,
    env_steps_per_second,
    fused_adam_overrides,
    higher_level_seconds,
    interleaved_seconds,
    profile_variants,
    repeat_call,
    run_model,
    run_profiles,
    run_throughput,
    run_updates,
    throughput_models,
    train_within_run,
    training_chunks,
    update_steps,
    variant_overrides,
)
from benchmarking.report import (
    BENCHMARKS_MD,
    CSV_COLUMNS,
    CSV_METRICS,
    OPTION_METRICS,
    PREFERENCE_PAIRS,
    PREFERENCE_PAIRS_KEY,
    REPO,
    RESULTS_DIR,
    TRAINING_SUCCESS,
    Curves,
    SeedCurve,
    command_line,
    final_mean,
    load_curves,
    machine,
    read_report_csv,
    report,
    run_seed_curve,
    task_table,
    write_section,
)
from benchmarking.run import (
    CPU_TASKS,
    DEFAULT_VARIANT,
    LEARNING_DEFAULTS,
    PAPER_ALGORITHMS,
    PAPER_TASKS,
    PARTS,
    POINT_MAZE,
    PROTOCOLS,
    RESULT,
    add_part_seconds,
    finished,
    learning_run,
    local_results,
    model_steps,
    ray_results,
    resolve_protocol,
    resumable,
    run_name,
    seed_folder,
    trained_to_the_end,
    zoo_flags,
    zoo_pairs,
)
from configs import ALGORITHMS, ZOO_KEYS, load_entry, make_env, make_model, torch_threads
from plot import LABELS, label

from sb3_dipper.common.files import write_bytes_atomically

# The parts of the benchmarks live in benchmarking/; their names stay importable from this script's module.
__all__ = [
    "ALGORITHMS",
    "BENCHMARKS_MD",
    "CPU_TASKS",
    "CSV_COLUMNS",
    "CSV_METRICS",
    "DEFAULT_VARIANT",
    "FUSED_ADAM",
    "LABELS",
    "LEARNING_DEFAULTS",
    "OPTION_METRICS",
    "PAPER_ALGORITHMS",
    "PAPER_TASKS",
    "PARTS",
    "POINT_MAZE",
    "PREFERENCE_PAIRS",
    "PREFERENCE_PAIRS_KEY",
    "PROTOCOLS",
    "REPO",
    "RESULT",
    "RESULTS_DIR",
    "THROUGHPUT_LOWER",
    "TRAINING_SUCCESS",
    "ZOO_KEYS",
    "Curves",
    "SeedCurve",
    "add_part_seconds",
    "command_line",
    "env_steps_per_second",
    "final_mean",
    "finished",
    "fused_adam_overrides",
    "higher_level_seconds",
    "interleaved_seconds",
    "label",
    "learning_run",
    "load_curves",
    "load_entry",
    "local_results",
    "machine",
    "make_env",
    "make_model",
    "model_steps",
    "profile_variants",
    "ray_results",
    "read_report_csv",
    "repeat_call",
    "report",
    "resolve_protocol",
    "resumable",
    "run_model",
    "run_name",
    "run_profiles",
    "run_seed_curve",
    "run_throughput",
    "run_updates",
    "seed_folder",
    "task_table",
    "throughput_models",
    "torch_threads",
    "train_within_run",
    "trained_to_the_end",
    "training_chunks",
    "update_steps",
    "variant_overrides",
    "write_section",
    "zoo_flags",
    "zoo_pairs",
]


def run_learning(args: argparse.Namespace) -> tuple[dict[str, str], dict[str, dict[str, Curves]]]:
    """The ``learning`` command, its arguments resolved (:func:`resolve_protocol`) and checked by :func:`main`."""
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
        write_bytes_atomically(figure.with_suffix(".csv"), (out / f"{args.name}.csv").read_bytes())
    print(f"{description}\n\n{tables_text}\n\nFigure: {figure}\nCSV: {out / f'{args.name}.csv'}")
    return tables, curves


def check_learning_arguments(args: argparse.Namespace, learning: argparse.ArgumentParser) -> None:
    """Refuse, before any run folder is made, the algorithms, tasks, numbers and overrides every run would fail on or
    silently change (``args`` resolved by :func:`resolve_protocol`)."""
    negative_seeds = [str(seed) for seed in args.seeds if seed < 0]
    if negative_seeds:
        # rl-zoo3 would replace it with a random seed, and the run filed as seed_-1 could not be repeated.
        learning.error(f"--seeds {' '.join(negative_seeds)}: a seed is >= 0 (rl-zoo3 draws a random one for a negative)")
    if args.n_timesteps is not None and args.n_timesteps < 1:
        # rl-zoo3 trains a -n below 1 to the YAML budget, while the report would state this one.
        learning.error(f"--n-timesteps {args.n_timesteps}: must be >= 1 primitive step; leave it out for each entry's budget")
    at_least_one = {
        "--eval-freq": (args.eval_freq, "primitive steps between evaluations, the points of the report's curves"),
        "--eval-episodes": (args.eval_episodes, "episodes per evaluation"),
        "--n-eval-envs": (args.n_eval_envs, "evaluation envs; leave it out for --eval-episodes, at most 10"),
        "--workers": (args.workers, "runs at a time on this machine"),
        "--save-freq": (args.save_freq, "primitive steps between kept models; leave it out to keep none"),
    }
    for flag, (value, meaning) in at_least_one.items():
        if value is not None and value < 1:
            learning.error(f"{flag} {value}: must be >= 1 ({meaning})")
    # A repeated value would start the same run twice at once (in one folder) and count its seed twice in the tables.
    for flag, values in (("--algos", args.algos), ("--envs", args.envs), ("--seeds", args.seeds)):
        repeated = sorted({str(value) for value in values if values.count(value) > 1})
        if repeated:
            learning.error(f"{flag} {' '.join(repeated)}: given more than once; name each once")
    unknown_algos = [algo for algo in args.algos if algo not in ALGORITHMS]
    if unknown_algos:
        known = " ".join(ALGORITHMS)
        learning.error(f"--algos {' '.join(unknown_algos)}: not a zoo name of hyperparams/; choose from {known}")
    for env_id in args.envs:
        if env_id not in gym.registry:
            closest = difflib.get_close_matches(env_id, list(gym.registry), n=1)
            hint = f"did you mean {closest[0]}?" if closest else "the tasks are listed in docs/guide/environments.rst"
            learning.error(f"--envs {env_id}: no such registered env; {hint}")
    try:
        zoo_pairs("--set", args.set)
        zoo_pairs("--env-kwargs", args.env_kwargs)
    except ValueError as error:
        learning.error(str(error))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    throughput = commands.add_parser("throughput", help="seconds per primitive step relative to SAC+HER")
    throughput.add_argument("--env", default="PointMazeFourRooms-v0")
    throughput.add_argument("--steps", type=int, default=1000)
    throughput.add_argument("--repeats", type=int, default=5)
    throughput.add_argument("--net-arch", type=int, nargs="+", default=[256, 256])
    throughput.add_argument("--write", action="store_true", help="write docs/benchmarks/throughput.json and its section")
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
        "folder), e.g. for zoo_scripts/research/planner_share.py --checkpoints",
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
        resolve_protocol(args)
        check_learning_arguments(args, learning)
    commands_run = {"throughput": run_throughput, "profiles": run_profiles, "updates": run_updates, "learning": run_learning}
    commands_run[args.command](args)


if __name__ == "__main__":
    main()
