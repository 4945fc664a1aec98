"""zoo_scripts/benchmark.py learning: its runs are zoo run folders, a rerun after a kill redoes only the unfinished run,
the per-task report reads the runs with plot.py, BENCHMARKS.md is written only with --write, and runs on a Ray cluster."""

import argparse
import json
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.test_files import truncate
from zoo_scripts import benchmark, plot
from zoo_scripts.benchmarking.run import ray_runtime_env

SCRIPT = Path(benchmark.__file__)
ENV_ID = "PointMazeFourRooms-v0"
# 300 steps of one env with 50-step episodes: the lower level trains from step 150 on small batches, so a run takes
# seconds but goes through collection, training, option metrics (logged every 4 episodes) and two evaluations.
TINY = [
    "--n-timesteps", "300", "--eval-freq", "150", "--eval-episodes", "2", "--env-kwargs", "max_episode_steps=50",
    "--set", "n_envs=1", "learning_starts=150", "batch_size=32", "buffer_size=2000",
]  # fmt: skip


CSV_HEADER = (
    "env,algo,seed,timesteps,success,subgoal_distance,low_value,train_success,preference_pairs,finished,steps_per_second"
)


def learning_command(out: Path, *args: str) -> list[str]:
    """``benchmark.py learning`` on the fast maze with tiny budgets, writing into ``out``."""
    return [sys.executable, str(SCRIPT), "learning", "--envs", ENV_ID, *TINY, "--out", str(out), *args]


def run_folder(out: Path, algo: str, seed: int, variant: str = "default") -> Path:
    return out / variant / f"seed_{seed}" / algo / f"{ENV_ID}_1"


def wait_for(path: Path, process: subprocess.Popen, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert process.poll() is None, f"exited with {process.returncode} before {path} appeared"
        assert time.monotonic() < deadline, f"{path} did not appear within {timeout} s"
        time.sleep(0.1)


@pytest.fixture(scope="module")
def resumed(tmp_path_factory):
    """HIER, seeds 0 and 1, one at a time: killed once seed 1's zoo run has started, then the same command again.

    :return: the output folder, seed 0's result.json (text and mtime) before the rerun, and the rerun
    """
    out = tmp_path_factory.mktemp("benchmark")
    command = learning_command(out, "--algos", "hier", "--seeds", "0", "1", "--workers", "1")
    # Its own session, so that the kill takes the zoo process with it, as a crash of the machine's job would.
    process = subprocess.Popen(command, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_for(run_folder(out, "hier", 0) / "result.json", process, timeout=300)
        wait_for(run_folder(out, "hier", 1), process, timeout=300)
    finally:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
    first = run_folder(out, "hier", 0) / "result.json"
    before = (first.read_text(), first.stat().st_mtime_ns)
    assert not (run_folder(out, "hier", 1) / "result.json").exists(), "seed 1 finished before the kill"
    rerun = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    return out, before, rerun


def test_a_rerun_after_a_kill_redoes_only_the_unfinished_run(resumed):
    out, (content, mtime), rerun = resumed
    assert "1 runs to do, 1 already finished" in rerun.stdout
    first = run_folder(out, "hier", 0) / "result.json"
    assert first.read_text() == content and first.stat().st_mtime_ns == mtime
    # The killed attempt's folder was removed, so the redone run is <env>_1 again, finished.
    assert json.loads((run_folder(out, "hier", 1) / "result.json").read_text())["seed"] == 1
    assert sorted(path.name for path in run_folder(out, "hier", 1).parent.iterdir()) == [f"{ENV_ID}.log", f"{ENV_ID}_1"]


def test_each_run_is_the_zoo_run_a_user_would_start(resumed):
    out, _, _ = resumed
    run = run_folder(out, "hier", 1)
    command = (run / ENV_ID / "command.txt").read_text().split()
    assert command[1:9] == ["-m", "sb3_dipper.zoo", "train", "--algo", "hier", "--env", ENV_ID, "--seed"]
    assert command[command.index("-params") + 1 :] == ["n_envs:1", "learning_starts:150", "batch_size:32", "buffer_size:2000"]
    # config.yml is the YAML entry with the -params overrides, its callback included (the zoo writes an OrderedDict).
    config = dict(yaml.unsafe_load((run / ENV_ID / "config.yml").read_text()))
    assert config["callback"] == "sb3_dipper.zoo.CSVProgressCallback" and config["learning_starts"] == 150
    assert (run / ENV_ID / "args.yml").exists() and (run / f"{ENV_ID}.zip").exists()
    assert "is_success" in (run / "0.monitor.csv").read_text().splitlines()[1]
    # SB3's EvalCallback: its keys, and successes because the env reports is_success.
    with np.load(run / "evaluations.npz") as data:
        assert set(data.files) == {"timesteps", "results", "ep_lengths", "successes"}
        assert list(data["timesteps"]) == [150, 300] and data["successes"].shape == (2, 2)
    header = (run / "progress.csv").read_text().splitlines()[0].split(",")
    assert {"rollout/subgoal_distance", "rollout/low_value", "eval/success_rate"} <= set(header)


def test_the_report_and_plot_py_read_the_runs_alike(resumed):
    out, _, rerun = resumed
    row = next(line for line in rerun.stdout.splitlines() if line.startswith("| HIER |"))
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    assert cells[1:3] == ["2", "300"]
    assert 0 <= float(cells[4]) <= 1  # training success, from the monitor files
    assert float(cells[6]) > 0  # subgoal distance, from progress.csv
    assert f"Figure: {out / 'learning.png'}" in rerun.stdout and (out / "learning.png").exists()
    csv = (out / "learning.csv").read_text().splitlines()
    assert csv[0] == CSV_HEADER
    assert len(csv) == 1 + 2 * 2
    seeds = [out / "default" / f"seed_{seed}" for seed in (0, 1)]
    fig = plot.plot_success(seeds, ["hier"], [ENV_ID])
    np.testing.assert_array_equal(fig.axes[0].get_lines()[0].get_xdata(), [150, 300])
    assert f"{fig.axes[0].get_lines()[0].get_ydata()[-1]:.2f}" == cells[3].split(" +- ")[0]
    assert plot.plot_hierarchical_metrics(seeds, ["hier"], [ENV_ID]) is not None
    assert plot.final_success_iqm(seeds, ["hier"], [ENV_ID], reps=20)["n_runs"].tolist() == [2]
    assert not list(out.rglob("BENCHMARKS.md"))


def write_monitor(folder: Path, lengths: list[int], successes: list[float]) -> None:
    """An SB3 monitor file with the is_success column, as the zoo's envs write it."""
    folder.mkdir(parents=True, exist_ok=True)
    episodes = enumerate(zip(lengths, successes, strict=True))
    rows = [f"-1.0,{length},{index}.0,{success}" for index, (length, success) in episodes]
    (folder / "0.monitor.csv").write_text("\n".join(['#{"t_start": 0.0, "env_id": "x"}', "r,l,t,is_success", *rows]) + "\n")


def write_run(
    out: Path,
    name: str,
    env_id: str,
    seed: int,
    successes: list[float],
    hierarchical: bool,
    finished: bool = True,
    training_successes: list[float] | None = None,
    seconds: float | None = None,
) -> None:
    """A zoo run folder of ``<algo>[-<variant>]`` as a benchmark leaves it: evaluations every 1,000 steps, progress.csv
    for a hierarchical algorithm, result.json once finished (with ``seconds``: its wall time, and the final model's
    zip, trained to the last evaluation), and a monitor file of 500-step training episodes."""
    algo, _, variant = name.partition("-")
    run = out / (variant or "default") / f"seed_{seed}" / algo / f"{env_id}_1"
    run.mkdir(parents=True)
    if training_successes is not None:
        write_monitor(run, [500] * len(training_successes), training_successes)
    steps = 1000 * np.arange(1, len(successes) + 1)
    if finished:
        (run / "result.json").write_text(json.dumps({} if seconds is None else {"seconds": seconds}))
    if finished and seconds is not None:
        with zipfile.ZipFile(run / f"{env_id}.zip", "w") as model:
            model.writestr("data", json.dumps({"num_timesteps": int(steps[-1]), "_total_timesteps": int(steps[-1])}))
    success = np.repeat(np.array(successes)[:, None], 4, axis=1)
    np.savez(
        run / "evaluations.npz", timesteps=steps, results=success - 1, ep_lengths=np.full_like(success, 50), successes=success
    )
    if hierarchical:
        # Logged between evaluations, and once after the last one: the value at an evaluation is the last logged by then.
        distances = [*np.linspace(2.0, 1.0, len(successes)), 9.0]
        # DIPPER (and its variants) label pairs: 10 more between evaluations; the others log no preference pairs.
        pairs = [f",{10 * (index + 1)}" if algo == "dipper" else "," for index in range(len(distances))]
        rows = [
            f"{step - 500},{distance},-3.0{labelled}"
            for step, distance, labelled in zip([*steps, steps[-1] + 1000], distances, pairs, strict=True)
        ]
        header = "time/total_timesteps,rollout/subgoal_distance,rollout/low_value,train/high_preference_pairs"
        (run / "progress.csv").write_text("\n".join([header, *rows]))


def test_report_per_task(tmp_path, monkeypatch):
    """One table per task with a row per algorithm (and variant), option metrics where logged, one panel per task,
    drawn by plot.py from the table's curves."""
    envs = [ENV_ID, "FetchPush-v4"]
    for env_id in envs:
        for seed in (0, 1):
            training = [0, 0, 0, 1, 1, 1]
            seconds = 30.0 * (seed + 1)  # 3,000 steps: 100 and 50 steps/s
            write_run(tmp_path, "dipper", env_id, seed, [0.0, 0.5, 1.0], True, training_successes=training, seconds=seconds)
            write_run(tmp_path, "sac", env_id, seed, [0.0, 0.25, 0.5], hierarchical=False)
    write_run(tmp_path, "dipper-no-plan", ENV_ID, 0, [0.0, 0.25, 0.25], hierarchical=True)
    # A seed still running: the table and the mean curve stop at the evaluations every seed has; the CSV has all of
    # them, and the figure continues the finished seed alone as a dotted line.
    write_run(tmp_path, "hier", ENV_ID, 0, [0.0, 0.0, 0.25], hierarchical=True)
    write_run(tmp_path, "hier", ENV_ID, 1, [0.0, 0.5], hierarchical=True, finished=False)
    names = ["dipper", "dipper-no-plan", "hier", "sac"]
    drawn = []
    draw_success = benchmark.plot.draw_success

    def draw_and_keep(panels):
        drawn.append(draw_success(panels))
        return drawn[-1]

    monkeypatch.setattr(benchmark.plot, "draw_success", draw_and_keep)

    tables, curves, figure = benchmark.report(tmp_path, names, envs, [0, 1], "report", tmp_path / "figures")

    assert list(curves[ENV_ID]) == names and list(curves["FetchPush-v4"]) == ["dipper", "sac"]
    assert curves[ENV_ID]["hier"].success.shape == (2, 2)
    rows = {line.split(" | ")[0].strip("| "): line for line in tables[ENV_ID].splitlines()[2:]}
    assert list(rows) == ["DIPPER", "DIPPER (no-plan)", "HIER", "SAC+HER"]
    assert rows["DIPPER"].startswith("| DIPPER | 2 | 3,000 |")
    # Training success: the last 100 training episodes finished by the last evaluation (3 of 6 succeeded).
    # Steps per second of wall time: the finished runs that recorded it (the others: a dash).
    assert rows["DIPPER"].endswith("| 1.00 +- 0.00 | 0.50 | 2,000 | 1.00 | -3.00 | 30 | 75 |")
    assert rows["DIPPER (no-plan)"].endswith("| 1 | 3,000 | 0.25 +- 0.00 | - | not reached | 1.00 | -3.00 | 30 | - |")
    assert rows["SAC+HER"].endswith("| 0.50 +- 0.00 | - | 3,000 | - | - | - | - |")
    assert rows["HIER"].startswith("| HIER | 2 (1 partial) | 2,000 | 0.25 +- 0.25 | - | not reached | 1.25 |")
    assert len(tables["FetchPush-v4"].splitlines()) == 2 + 2
    csv = (tmp_path / "report.csv").read_text().splitlines()
    assert csv[0] == CSV_HEADER
    assert {line.split(",")[0] for line in csv[1:]} == set(envs)
    assert f"{ENV_ID},hier,1,2000,0.5000,1.0000,-3.0000,,,0," in csv
    assert f"{ENV_ID},hier,0,3000,0.2500,1.0000,-3.0000,,,1," in csv
    assert f"{ENV_ID},dipper,0,3000,1.0000,1.0000,-3.0000,0.5000,30.0000,1,100.0" in csv
    assert f"{ENV_ID},dipper,1,3000,1.0000,1.0000,-3.0000,0.5000,30.0000,1,50.0" in csv
    assert figure == tmp_path / "figures" / "report.png" and figure.exists()
    lines = [[line.get_label() for line in ax.get_lines() if line.get_linestyle() == "-"] for ax in drawn[0].axes]
    assert lines == [["DIPPER", "DIPPER (no-plan)", "HIER", "SAC+HER"], ["DIPPER", "SAC+HER"]]
    np.testing.assert_allclose(drawn[0].axes[0].get_lines()[2].get_ydata(), curves[ENV_ID]["hier"].success.mean(axis=0))
    (continued,) = [line for ax in drawn[0].axes for line in ax.get_lines() if line.get_linestyle() == ":"]
    np.testing.assert_allclose(continued.get_xdata(), [2000, 3000])
    np.testing.assert_allclose(continued.get_ydata(), [0.0, 0.25])


def test_a_task_without_runs_says_so_instead_of_an_empty_table(tmp_path):
    write_run(tmp_path, "dipper", ENV_ID, 0, [0.0, 0.5], hierarchical=True)

    table, curves, csv_rows = benchmark.task_table(tmp_path, ["dipper", "sac"], "FetchPush-v4", [0], {})

    assert (table, curves, csv_rows) == ("No runs yet.", {}, [])


def test_a_later_report_takes_the_runs_whose_folders_are_gone_from_the_earlier_csv(tmp_path):
    """Run folders do not outlive their machine; the CSV does. A report from the CSV alone is the report from the
    folders (tables, partial runs, CSV); a seed with a folder on disk is read from the folder, the others from the CSV."""
    first, later = tmp_path / "first", tmp_path / "later"
    for seed in (0, 1):
        write_run(first, "dipper", ENV_ID, seed, [0.0, 0.5, 1.0], True, training_successes=[0, 1], seconds=20.0 + seed)
        write_run(first, "sac", ENV_ID, seed, [0.0, 0.25, 0.5], hierarchical=False)
    write_run(first, "hier", ENV_ID, 0, [0.0, 0.0, 0.25], hierarchical=True)
    write_run(first, "hier", ENV_ID, 1, [0.0, 0.5], hierarchical=True, finished=False)
    names, seeds = ["dipper", "hier", "sac"], [0, 1]
    tables, _, _ = benchmark.report(first, names, [ENV_ID], seeds, "report", first)
    previous = benchmark.read_report_csv(first / "report.csv")

    later.mkdir()
    again, curves, _ = benchmark.report(later, names, [ENV_ID], seeds, "report", later, previous)
    assert again == tables
    assert (later / "report.csv").read_text() == (first / "report.csv").read_text()
    assert curves[ENV_ID]["hier"].finished == [True, False]

    # A new run of seed 1 on disk replaces the CSV's seed 1; seed 0 still comes from the CSV.
    write_run(later, "sac", ENV_ID, 1, [1.0, 1.0, 1.0], hierarchical=False)
    mixed, _, _ = benchmark.report(later, names, [ENV_ID], seeds, "report", later, previous)
    sac = next(line for line in mixed[ENV_ID].splitlines() if line.startswith("| SAC+HER |"))
    assert sac.startswith("| SAC+HER | 2 | 3,000 | 0.75 +- 0.25 |")


def test_a_damaged_evaluation_record_leaves_out_an_unfinished_run_and_stops_a_finished_one(tmp_path):
    """A record cut short (a run killed while SB3 rewrote it in place) stopped the whole report with a BadZipFile
    naming no file. An unfinished run's is reported as no evaluation yet, with a warning naming the file; a finished
    run's is an error naming it."""
    write_run(tmp_path, "dipper", ENV_ID, 0, [0.0, 0.5, 1.0], hierarchical=True)
    write_run(tmp_path, "dipper", ENV_ID, 1, [0.0, 0.5], hierarchical=True, finished=False)
    unfinished = run_folder(tmp_path, "dipper", 1) / "evaluations.npz"
    truncate(unfinished)
    with pytest.warns(UserWarning, match=rf"{re.escape(str(unfinished))}: not a complete npz archive.* not evaluated yet"):
        table, curves, _ = benchmark.task_table(tmp_path, ["dipper"], ENV_ID, [0, 1], {})
    assert curves["dipper"].seeds == [0]
    assert "| DIPPER | 1 | 3,000 | 1.00 +- 0.00 |" in table

    finished = run_folder(tmp_path, "dipper", 0) / "evaluations.npz"
    truncate(finished)
    with pytest.raises(ValueError, match=rf"{re.escape(str(finished))}: not a complete npz archive"):
        benchmark.task_table(tmp_path, ["dipper"], ENV_ID, [0, 1], {})


def test_a_csv_without_the_report_s_columns_is_refused(tmp_path):
    old = tmp_path / "old.csv"
    old.write_text(f"{CSV_HEADER.removesuffix(',finished,steps_per_second')}\n{ENV_ID},dipper,0,1000,0.0,,,,\n")
    with pytest.raises(ValueError, match=r"old\.csv lacks the columns \['finished'\]"):
        benchmark.read_report_csv(old)


def test_benchmarks_md_is_written_only_with_write(tmp_path, monkeypatch, capsys):
    """--report-only runs nothing and reports the partial runs on disk; without --write the tables are printed and the
    figure lands in --out, with --write the section goes into BENCHMARKS.md and the figure into docs/benchmarks."""
    repository = tmp_path / "repository"
    monkeypatch.setattr(benchmark, "BENCHMARKS_MD", repository / "BENCHMARKS.md")
    monkeypatch.setattr(benchmark, "RESULTS_DIR", repository / "docs" / "benchmarks")
    out = tmp_path / "out"
    write_run(out, "dipper", ENV_ID, 0, [0.0, 0.5], hierarchical=True, finished=False)
    argv = ["benchmark.py", "learning", "--report-only", "--algos", "dipper", "sac", "--seeds", "0", "--envs", ENV_ID]
    argv += ["--name", "partial", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", argv)
    benchmark.main()
    printed = capsys.readouterr().out
    assert "2 runs to do, 0 already finished" in printed
    assert "| DIPPER | 1 (1 partial) | 2,000 | 0.50 +- 0.00 |" in printed
    assert not (out / "default" / "seed_0" / "sac").exists()
    assert (out / "partial.png").exists() and (out / "partial.csv").exists() and not repository.exists()

    monkeypatch.setattr(sys, "argv", [*argv, "--write"])
    benchmark.main()
    section = (repository / "BENCHMARKS.md").read_text()
    assert "<!-- partial:start -->" in section and "| DIPPER | 1 (1 partial) | 2,000 | 0.50 +- 0.00 |" in section
    assert "![success curves](docs/benchmarks/partial.png)" in section
    assert (repository / "docs" / "benchmarks" / "partial.png").exists()
    assert (repository / "docs" / "benchmarks" / "partial.csv").read_text() == (out / "partial.csv").read_text()

    monkeypatch.setattr(sys, "argv", [*argv, "--benchmarks-md", str(tmp_path / "elsewhere.md")])
    with pytest.raises(SystemExit):
        benchmark.main()
    assert "add --write" in capsys.readouterr().err

    monkeypatch.setattr(sys, "argv", [*argv, "--previous-csv", str(tmp_path / "gone.csv")])
    with pytest.raises(SystemExit):
        benchmark.main()
    assert "--previous-csv" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--algos", "dipperx"], "--algos dipperx: not a zoo name of hyperparams/; choose from dipper "),
        (["--envs", "FetchPickAndPlaceFixd-v0"], "did you mean FetchPickAndPlaceFixed-v0?"),
        (["--set", "beta=0.1)"], "--set beta=0.1): '0.1)' is not a Python expression"),
        (["--set", "preference_source=progress"], "quote a string"),
        (["--env-kwargs", "max_episode_steps"], "--env-kwargs takes key=value"),
        (["--seeds", "0", "1", "0"], "--seeds 0: given more than once; name each once"),
        (["--algos", "sac", "sac"], "--algos sac: given more than once"),
    ],
)
def test_learning_refuses_what_every_run_would_fail_on_before_making_a_folder(
    tmp_path, monkeypatch, capsys, arguments, message
):
    """An unknown algorithm or task, a repeated value, or an override rl-zoo3 cannot read, fails every run: the
    command says so at once, naming the option, and makes no run folder."""
    out = tmp_path / "out"
    argv = ["benchmark.py", "learning", "--algos", "dipper", "--envs", ENV_ID, "--seeds", "0", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", [*argv, *arguments])
    with pytest.raises(SystemExit) as exited:
        benchmark.main()
    assert exited.value.code == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--seeds", "0", "-1"], "--seeds -1: a seed is >= 0 (rl-zoo3 draws a random one for a negative)"),
        (["--n-timesteps", "-5"], "--n-timesteps -5: must be >= 1 primitive step; leave it out for each entry's budget"),
        (["--n-timesteps", "0"], "--n-timesteps 0: must be >= 1"),
        (["--eval-freq", "0"], "--eval-freq 0: must be >= 1 (primitive steps between evaluations"),
        (["--protocol", "quick", "--eval-freq", "-8000"], "--eval-freq -8000: must be >= 1"),
        (["--eval-episodes", "0"], "--eval-episodes 0: must be >= 1 (episodes per evaluation)"),
        (["--n-eval-envs", "0"], "--n-eval-envs 0: must be >= 1 (evaluation envs; leave it out for --eval-episodes"),
        (["--workers", "0"], "--workers 0: must be >= 1 (runs at a time on this machine)"),
        (["--save-freq", "0"], "--save-freq 0: must be >= 1 (primitive steps between kept models; leave it out"),
    ],
)
def test_learning_refuses_numbers_that_would_change_or_stop_every_run(tmp_path, monkeypatch, capsys, arguments, message):
    """The reported case: all of these were accepted. rl-zoo3 draws a random seed for a negative one (filed as seed_-1,
    never to be repeated) and trains a -n below 1 to the YAML budget (the report stating the one given); no evaluation
    leaves a finished run without a curve; --workers 0 failed in the thread pool, naming no flag. With --report-only,
    so that nothing would train even if a value got through."""
    out = tmp_path / "out"
    argv = ["benchmark.py", "learning", "--algos", "sac", "--envs", ENV_ID, "--seeds", "0", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", [*argv, "--report-only", *arguments])
    with pytest.raises(SystemExit) as exited:
        benchmark.main()
    assert exited.value.code == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_overrides_become_the_zoo_s_flags():
    args = argparse.Namespace(
        eval_freq=150, eval_episodes=20, n_eval_envs=None, n_timesteps=None, pause_after_minutes=None, save_freq=None
    )
    args.set = ["planning='off'", "low_policy_kwargs=dict(net_arch=[16])", "switch_kwargs=dict(nll_coef=0.0)"]
    args.env_kwargs = ["max_episode_steps=50"]
    flags = benchmark.zoo_flags(args)
    assert flags[:6] == ["--eval-freq", "150", "--eval-episodes", "20", "--n-eval-envs", "10"]
    assert flags[6:] == [
        "--env-kwargs", "max_episode_steps:50",
        "-params", "planning:'off'", "low_policy_kwargs:dict(net_arch=[16])", "switch_kwargs:dict(nll_coef=0.0)",
    ]  # fmt: skip
    args.pause_after_minutes = 80.0
    assert benchmark.zoo_flags(args)[6:8] == ["--pause-after-minutes", "80.0"]
    args.save_freq = 300
    assert benchmark.zoo_flags(args)[8:10] == ["--save-freq", "300"]
    with pytest.raises(ValueError, match="quote a string: --set \"planning='off'\""):
        benchmark.zoo_pairs("--set", ["planning=off"])
    for malformed in ("planning", "=1", "beta=0.1)"):
        with pytest.raises(ValueError, match="--set"):
            benchmark.zoo_pairs("--set", [malformed])


def test_a_run_counts_as_finished_only_when_its_model_trained_the_whole_budget(tmp_path):
    """rl-zoo3 saves the model of a run stopped by Ctrl-C too: its step count tells it apart."""
    run = tmp_path / f"{ENV_ID}_1"
    run.mkdir()
    assert not benchmark.trained_to_the_end(run)
    for steps, expected in ((200, False), (300, True)):
        with zipfile.ZipFile(run / f"{ENV_ID}.zip", "w") as archive:
            archive.writestr("data", json.dumps({"num_timesteps": steps, "_total_timesteps": 300}))
        assert benchmark.trained_to_the_end(run) is expected


def test_protocol_presets_yield_to_flags():
    args = argparse.Namespace(protocol="quick", envs=None, algos=["sac"], seeds=None, name=None)
    args.n_timesteps = args.eval_freq = args.eval_episodes = None
    benchmark.resolve_protocol(args)
    assert args.algos == ["sac"] and args.envs == [ENV_ID] and args.seeds == [0, 1, 2] and args.name == "quick"
    assert (args.n_timesteps, args.eval_freq, args.eval_episodes) == (40_000, 8_000, 20)
    assert set(benchmark.PROTOCOLS["quick"]["algos"]) == set(benchmark.LABELS) - {"tqc"}


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture
def ray_head():
    """A one-node Ray cluster on loopback with 2 CPUs, stopped with everything it started."""
    pytest.importorskip("ray")
    port = free_port()
    # A short private directory: Ray's socket paths must fit in 107 characters and must not meet another cluster's.
    temp_dir = tempfile.mkdtemp(prefix="ray-", dir="/tmp")
    log = Path(temp_dir) / "head.log"
    command = [
        str(Path(sys.executable).with_name("ray")), "start", "--head", "--block", "--node-ip-address", "127.0.0.1",
        "--port", str(port), "--num-cpus", "2", "--include-dashboard=false", "--disable-usage-stats",
        "--temp-dir", temp_dir,
    ]  # fmt: skip
    with open(log, "w") as output:
        head = subprocess.Popen(command, stdout=output, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while "Ray runtime started" not in log.read_text():
            assert head.poll() is None and time.monotonic() < deadline, log.read_text()[-3000:]
            time.sleep(0.2)
        yield f"127.0.0.1:{port}"
    finally:
        # --block: SIGTERM makes `ray start` stop the processes it started; the group kill catches stragglers.
        head.terminate()
        try:
            head.wait(timeout=30)
        finally:
            try:
                os.killpg(head.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            shutil.rmtree(temp_dir, ignore_errors=True)


def test_ray_runs(tmp_path, ray_head):
    """--ray-address: the same zoo run as a Ray task, written into the same --out layout."""
    command = learning_command(tmp_path, "--algos", "sac", "--seeds", "0", "--ray-address", ray_head)
    environment = dict(os.environ, RAY_USAGE_STATS_ENABLED="0")
    result = subprocess.run(command, capture_output=True, text=True, timeout=300, env=environment)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "1 runs to do, 0 already finished" in result.stdout
    assert (run_folder(tmp_path, "sac", 0) / "result.json").exists()
    # SAC's YAML entry has no CSVProgressCallback: a flat algorithm logs no option metrics, its row shows dashes.
    assert not (run_folder(tmp_path, "sac", 0) / "progress.csv").exists()
    # ... and the finished run's steps per second close it.
    row = next(line for line in result.stdout.splitlines() if line.startswith("| SAC+HER |"))
    assert re.search(r"\| - \| - \| - \| \d+ \|$", row), row
    assert (tmp_path / "learning.png").exists()
    # Its task ran at the cluster's priority, not at the niceness of 15 Ray gives its workers (beside any other load, the
    # training starved).
    import ray

    ray.init(address=ray_head, runtime_env=ray_runtime_env())
    try:
        niceness = ray.get(ray.remote(num_cpus=1)(lambda: os.nice(0)).remote())
    finally:
        ray.shutdown()
    assert niceness == os.getpriority(os.PRIO_PROCESS, 0) == 0


def profiles_args(**changes):
    """``benchmark.py profiles``'s arguments: one chunk of 100 steps of SAC+HER on the test task, nothing written."""
    defaults = dict(envs=[ENV_ID], algos=["sac"], steps=100, repeats=1, name="profiles", write=False, fused_adam=False)
    return argparse.Namespace(**{**defaults, "variant": [], **changes})


def test_profiles_measures_training_and_env_rates(capsys):
    benchmark.run_profiles(profiles_args(algos=["dipper", "sac"], steps=200))
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith(f"| `{ENV_ID}`")]
    assert [row.split(" | ")[1] for row in rows] == ["DIPPER", "SAC+HER"]
    for row in rows:
        train_rate, env_rate, to_env = (float(cell) for cell in row.split(" | ")[2:5])
        assert 0 < train_rate < env_rate and to_env == pytest.approx(train_rate / env_rate, abs=0.01)
    assert rows[1].endswith("| 1.00 | - |")  # SAC+HER has no higher level
    assert 0 < int(rows[0].split(" | ")[-1].rstrip(" |%")) < 100


def test_the_higher_level_s_share_is_the_time_train_spends_outside_the_lower_update():
    class Hierarchical:  # the methods run_profiles times, nothing else
        def _train_low_level(self):
            time.sleep(0.02)

        def train(self):
            self._train_low_level()
            time.sleep(0.03)

    model = Hierarchical()
    spent = benchmark.higher_level_seconds({"hier": model, "flat": object()})
    model.train()
    assert list(spent) == ["hier"]
    assert spent["hier"]["_train_low_level"] == pytest.approx(0.02, abs=0.01)
    assert spent["hier"]["train"] - spent["hier"]["_train_low_level"] == pytest.approx(0.03, abs=0.01)


@pytest.mark.parametrize("algo", ["dipper", "hier", "sac"])
def test_fused_adam_profiles_fuse_every_level_s_optimizers(algo):
    model = benchmark.make_model(algo, ENV_ID, seed=0, overrides=benchmark.fused_adam_overrides(algo, ENV_ID))[0]
    policies = [model.policy, *([model.lower.policy] if hasattr(model, "lower") else [])]
    optimizers = [module.optimizer for policy in policies for module in policy.modules() if hasattr(module, "optimizer")]
    assert len(optimizers) >= (3 if hasattr(model, "lower") else 2)  # actor and critic of each SAC level
    assert all(optimizer.defaults["fused"] for optimizer in optimizers)
    profile_nets = benchmark.load_entry(algo, ENV_ID)["policy_kwargs"]["net_arch"]
    assert model.policy_kwargs["net_arch"] == profile_nets  # the fused copy keeps the profile's networks


def test_profiles_measure_each_variant_beside_the_profile(capsys):
    benchmark.run_profiles(profiles_args(variant=[["b64", "batch_size=64", "gradient_steps=2"]]))
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith(f"| `{ENV_ID}`")]
    assert [row.split(" | ")[1] for row in rows] == ["SAC+HER", "SAC+HER (b64)"]
    with pytest.raises(ValueError, match="none of sac takes bc_coef"):
        benchmark.run_profiles(profiles_args(variant=[["bc", "bc_coef=1.0"]]))


def test_a_variant_changes_only_what_it_names_and_skips_algorithms_without_the_keyword():
    fused = {"low_policy_kwargs": {"optimizer_kwargs": {"fused": True}}, "n_envs": 4}
    overrides = benchmark.variant_overrides("dipper", ENV_ID, fused)
    entry = benchmark.load_entry("dipper", ENV_ID)
    assert overrides == {"low_policy_kwargs": {**entry["low_policy_kwargs"], "optimizer_kwargs": {"fused": True}}, "n_envs": 4}
    assert benchmark.variant_overrides("sac", ENV_ID, fused) is None
    assert benchmark.variant_overrides("sac", ENV_ID, {"n_envs": 4}) == {"n_envs": 4}
    # A deprecated keyword is one the algorithm takes (into its demo_kwargs).
    assert benchmark.variant_overrides("dipper", ENV_ID, {"bc_coef": 1.0}) == {"bc_coef": 1.0}


def test_a_stamped_command_reruns_with_the_arguments_it_ran_with():
    arguments = ["learning", "--set", "planning='off'", "policy_kwargs={'net_arch': [64, 64]}", "--seeds", "0"]
    command = benchmark.command_line("benchmark.py", arguments)
    assert shlex.split(command) == ["python", "zoo_scripts/benchmark.py", *arguments]
    plain = benchmark.command_line("benchmark.py", ["profiles", "--write"])
    assert plain == "python zoo_scripts/benchmark.py profiles --write"  # nothing quoted that needs no quotes


def test_profile_variants_read_literals_and_refuse_what_is_not_one():
    variants = [["b128", "batch_size=128", "policy_kwargs={'net_arch': [64, 64]}"], ["n4", "n_envs=4"]]
    assert benchmark.profile_variants(variants) == {
        "b128": {"batch_size": 128, "policy_kwargs": {"net_arch": [64, 64]}},
        "n4": {"n_envs": 4},
    }
    with pytest.raises(ValueError, match="not a Python literal"):
        benchmark.profile_variants([["small", "policy_kwargs=dict(net_arch=[64])"]])
    with pytest.raises(ValueError, match="takes a name, then key=value"):
        benchmark.profile_variants([["batch_size=128"]])
    with pytest.raises(ValueError, match="takes key=value after its name"):
        benchmark.profile_variants([["b128", "batch_size"]])


def test_profiles_measure_the_fused_adam_copies_beside_the_profiles(capsys):
    benchmark.run_profiles(profiles_args(fused_adam=True))
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith(f"| `{ENV_ID}`")]
    assert [row.split(" | ")[1] for row in rows] == ["SAC+HER", "SAC+HER (fused)"]


def test_a_profile_chunk_trains_within_the_entrys_run_and_labels_on_its_schedule():
    model = benchmark.run_model("dipper", ENV_ID)
    assert model.run_budget == int(benchmark.load_entry("dipper", ENV_ID)["n_timesteps"])
    benchmark.train_within_run(model, model.learning_starts + 400)
    start = model.num_timesteps
    benchmark.train_within_run(model, 200)
    assert model._total_timesteps == model.run_budget
    assert 200 <= model.num_timesteps - start < 200 + model.n_envs
    # Labelled as a run of the entry's budget has it by now (a learn(steps) of its own ends its run every chunk and
    # labels the most pairs a round takes at every option).
    assert 0 < len(model.preferences) <= model.n_preference_pairs * model.num_timesteps / model.run_budget + 1


def test_throughput_writes_its_record_only_when_asked(tmp_path, monkeypatch, capsys):
    """A quick ``throughput`` check must not overwrite the committed record and its section."""
    from stable_baselines3 import SAC

    profile = sys.modules[benchmark.run_throughput.__module__]
    model = SAC("MlpPolicy", "Pendulum-v1", learning_starts=10, batch_size=8, policy_kwargs=dict(net_arch=[8]), seed=0)
    model.run_budget = 1000
    monkeypatch.setattr(profile, "throughput_models", lambda env_id, net_arch: {"sac": model})
    monkeypatch.setitem(profile.THROUGHPUT_LOWER, "learning_starts", 10)
    monkeypatch.setattr(profile, "RESULTS_DIR", tmp_path)
    sections = []
    monkeypatch.setattr(profile, "write_section", lambda name, body, command: sections.append(name))
    args = argparse.Namespace(env="Pendulum-v1", steps=20, repeats=1, net_arch=[8], write=False)
    benchmark.run_throughput(args)
    assert "| SAC+HER |" in capsys.readouterr().out
    assert not list(tmp_path.iterdir()) and not sections
    benchmark.run_throughput(argparse.Namespace(**{**vars(args), "write": True}))
    assert list(json.loads((tmp_path / "throughput.json").read_text())["median"]) == ["sac"]
    assert sections == ["throughput"]
