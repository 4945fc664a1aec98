"""zoo_scripts/benchmark.py learning: resuming after a crash, the per-task report, and runs on a local Ray cluster."""

import argparse
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from zoo_scripts import benchmark

SCRIPT = Path(benchmark.__file__)
ENV_ID = "PointMazeFourRooms-v0"
# 300 steps of one env with 200-step episodes: the lower level trains from step 250 on small batches, so a run takes
# seconds but goes through collection, training, option metrics and two evaluations.
TINY = [
    "--n-timesteps", "300", "--eval-freq", "150", "--eval-episodes", "2",
    "--set", "n_envs=1", "learning_starts=250", "batch_size=32",
]  # fmt: skip


def learning_command(out: Path, *args: str) -> list[str]:
    """``benchmark.py learning`` writing into ``out`` only (not the repository's BENCHMARKS.md and docs/)."""
    report = ["--out", str(out), "--benchmarks-md", str(out / "BENCHMARKS.md"), "--figures-dir", str(out / "figures")]
    return [sys.executable, str(SCRIPT), "learning", "--envs", ENV_ID, *TINY, *report, *args]


def result_path(out: Path, algo: str, seed: int) -> Path:
    return benchmark.run_directory(out, algo, ENV_ID, seed) / "result.json"


def wait_for(path: Path, process: subprocess.Popen, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert process.poll() is None, f"exited with {process.returncode} before {path} appeared"
        assert time.monotonic() < deadline, f"{path} did not appear within {timeout} s"
        time.sleep(0.1)


def test_resume_after_kill(tmp_path):
    """A crash loses only the run in progress: the rerun keeps finished runs untouched and completes the rest."""
    command = learning_command(tmp_path, "--algos", "hier", "--seeds", "0", "1", "--workers", "1")
    # Its own session, so that the kill takes the pool's worker with it, as a crash of the machine's job would.
    process = subprocess.Popen(command, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_for(result_path(tmp_path, "hier", 0), process, timeout=300)
    finally:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
    finished = result_path(tmp_path, "hier", 0)
    content, mtime = finished.read_text(), finished.stat().st_mtime_ns
    assert not result_path(tmp_path, "hier", 1).exists(), "seed 1 finished before the kill: nothing was interrupted"

    rerun = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert "1 runs to do, 1 already finished" in rerun.stdout
    assert finished.read_text() == content and finished.stat().st_mtime_ns == mtime
    assert result_path(tmp_path, "hier", 1).exists()
    with np.load(result_path(tmp_path, "hier", 1).parent / "evaluations.npz") as data:
        assert list(data["timesteps"]) == [150, 300]
        assert set(benchmark.OPTION_METRICS) <= set(data.files)
        assert np.isfinite(data["subgoal_distance"]).all()


def write_run(
    out: Path, algo: str, env_id: str, seed: int, successes: list[float], hierarchical: bool, finished: bool = True
) -> None:
    directory = benchmark.run_directory(out, algo, env_id, seed)
    directory.mkdir(parents=True)
    if finished:
        (directory / "result.json").write_text("{}")
    steps = 1000 * np.arange(1, len(successes) + 1)
    arrays = dict(timesteps=steps, successes=np.repeat(np.array(successes)[:, None], 4, axis=1))
    if hierarchical:
        arrays.update(subgoal_distance=np.linspace(2.0, 1.0, len(successes)), low_value=np.full(len(successes), -3.0))
    np.savez(directory / "evaluations.npz", **arrays)


def test_report_per_task(tmp_path):
    """One table per task with a row per algorithm, option metrics where recorded, one panel per task."""
    envs = [ENV_ID, "FetchPush-v4"]
    for env_id in envs:
        for seed in (0, 1):
            write_run(tmp_path, "dipper", env_id, seed, [0.0, 0.5, 1.0], hierarchical=True)
            write_run(tmp_path, "sac", env_id, seed, [0.0, 0.25, 0.5], hierarchical=False)
    # A seed still running: the curves stop at the evaluations every seed has.
    write_run(tmp_path, "hier", ENV_ID, 0, [0.0, 0.0, 0.25], hierarchical=True)
    write_run(tmp_path, "hier", ENV_ID, 1, [0.0, 0.0], hierarchical=True, finished=False)
    algos = ["dipper", "hier", "sac"]

    tables, curves, figure = benchmark.report(tmp_path, algos, envs, [0, 1], "report", tmp_path / "figures")

    assert list(curves[ENV_ID]) == algos and list(curves["FetchPush-v4"]) == ["dipper", "sac"]
    assert curves[ENV_ID]["hier"].success.shape == (2, 2)
    rows = {line.split(" | ")[0].strip("| "): line for line in tables[ENV_ID].splitlines()[2:]}
    assert list(rows) == ["DIPPER", "HIER", "SAC+HER"]
    assert "| 1.00 +- 0.00 | 2,000 | 1.00 | -3.00 |" in rows["DIPPER"]
    assert rows["SAC+HER"].endswith("| 0.50 +- 0.00 | 3,000 | - | - |")
    assert rows["DIPPER"].startswith("| DIPPER | 2 | 3,000 |")
    assert rows["HIER"].startswith("| HIER | 2 (1 partial) | 2,000 | 0.00 +- 0.00 |")
    assert len(tables["FetchPush-v4"].splitlines()) == 2 + 2
    csv = (tmp_path / "report.csv").read_text().splitlines()
    assert csv[0] == "env,algo,seed,timesteps,success,subgoal_distance,low_value"
    assert {line.split(",")[0] for line in csv[1:]} == set(envs)
    assert figure.exists()

    lines = benchmark.plot_curves(curves, tmp_path / "figures" / "again.png")
    assert lines == {ENV_ID: ["DIPPER", "HIER", "SAC+HER"], "FetchPush-v4": ["DIPPER", "SAC+HER"]}


def test_report_only_runs_nothing_and_reports_what_is_on_disk(tmp_path):
    write_run(tmp_path, "dipper", ENV_ID, 0, [0.0, 0.5], hierarchical=True, finished=False)
    command = [sys.executable, str(SCRIPT), "learning", "--report-only", "--algos", "dipper", "sac", "--seeds", "0"]
    command += ["--envs", ENV_ID, "--name", "partial", "--out", str(tmp_path)]
    command += ["--benchmarks-md", str(tmp_path / "BENCHMARKS.md"), "--figures-dir", str(tmp_path / "figures")]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "2 runs to do, 0 already finished" in done.stdout
    assert not benchmark.run_directory(tmp_path, "sac", ENV_ID, 0).exists()
    assert "| DIPPER | 1 (1 partial) | 2,000 | 0.50 +- 0.00 |" in (tmp_path / "BENCHMARKS.md").read_text()


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
    """--ray-address: the same runs as Ray tasks, written into the same --out layout."""
    command = learning_command(tmp_path, "--algos", "hier", "sac", "--seeds", "0", "1", "--ray-address", ray_head)
    environment = dict(os.environ, RAY_USAGE_STATS_ENABLED="0")
    result = subprocess.run(command, capture_output=True, text=True, timeout=300, env=environment)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "4 runs to do, 0 already finished" in result.stdout
    for algo in ("hier", "sac"):
        for seed in (0, 1):
            assert result_path(tmp_path, algo, seed).exists()
    with np.load(result_path(tmp_path, "sac", 0).parent / "evaluations.npz") as data:
        assert "subgoal_distance" not in data.files
    assert (tmp_path / "figures" / "learning.png").exists()
    assert "<!-- learning:start -->" in (tmp_path / "BENCHMARKS.md").read_text()


def test_profiles_measures_training_and_env_rates(capsys):
    args = argparse.Namespace(envs=[ENV_ID], algos=["dipper", "sac"], steps=200, repeats=1, name="profiles", write=False)
    benchmark.run_profiles(args)
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith(f"| `{ENV_ID}`")]
    assert [row.split(" | ")[1] for row in rows] == ["DIPPER", "SAC+HER"]
    for row in rows:
        train_rate, env_rate, to_env = (float(cell) for cell in row.split(" | ")[2:5])
        assert 0 < train_rate < env_rate and to_env == pytest.approx(train_rate / env_rate, abs=0.01)
    assert rows[1].endswith("| 1.00 |")
