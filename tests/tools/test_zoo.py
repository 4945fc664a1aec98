"""The RL-Zoo runner: our YAML files, ``sb3-dipper-zoo train`` / ``enjoy`` in subprocesses, and clear errors."""

import csv
import inspect
import os
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import optuna
import pandas as pd
import pytest
import yaml
from optuna.trial import TrialState
from stable_baselines3 import SAC
from stable_baselines3.common.callbacks import EvalCallback
from stable_baselines3.common.logger import CSVOutputFormat
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import SubprocVecEnv

from sb3_dipper import HIER
from sb3_dipper.common.files import npz_path
from sb3_dipper.zoo import (
    CONVERTERS,
    SAMPLERS,
    ZOO_ALGORITHMS,
    AtomicEvalCallback,
    CSVProgressCallback,
    claim_run_folder,
    hyperparams_dir,
    keep_params_without_value_term,
    main,
    run_control_parser,
    zoo_argv,
)
from sb3_dipper.zoo.callbacks import STEPS_KEY, AtomicCSVOutputFormat, read_progress
from tests.conftest import short_maze, tiny_model
from zoo_scripts.configs import ALGORITHMS, ZOO_KEYS, load_entry

ENV_ID = "PointMazeFourRooms-v0"
PAPER_TASKS = [
    "FetchFourRoomMaze-v0",
    "FetchFourRoomMazeFixed-v0",
    "FetchPickAndPlace-v4",
    "FetchPickAndPlaceFixed-v0",
    "FetchPush-v4",
    "FetchPushFixed-v0",
    "FrankaKitchenMicrowaveBurner-v0",
]
YAML_FILES = sorted(hyperparams_dir().glob("*.yml"))

# Test-sized overrides per algorithm class, passed through rl-zoo3's own `-params` flag.
TINY_HIERARCHICAL = [
    "n_envs:1",
    "option_steps:5",
    "learning_starts:50",
    "batch_size:16",
    "buffer_size:2000",
    "low_policy_kwargs:dict(net_arch=[16])",
    "policy_kwargs:dict(net_arch=[16])",
]
# dipper_paper and dipper_nov are DIPPER with other hyperparameters: the YAML tests check their entries and
# tests/tools/test_profiles.py builds them, so a train-and-enjoy subprocess pair of their own (~30 s each) would only repeat
# DIPPER's.
TINY_PARAMS = {
    "dipper": [*TINY_HIERARCHICAL, "n_preference_pairs:200", "pairs_per_batch:8", "trajectory_buffer_size:50"],
    "hier": [*TINY_HIERARCHICAL, "high_batch_size:16", "high_buffer_size:1000"],
    "piper": [
        *TINY_HIERARCHICAL,
        "high_batch_size:16",
        "high_buffer_size:1000",
        "n_preference_pairs:200",
        "reward_batch_size:8",
    ],
    "saga": [*TINY_HIERARCHICAL, "high_batch_size:16", "high_buffer_size:1000"],
    "hac": [*TINY_HIERARCHICAL, "high_batch_size:16", "high_buffer_size:1000"],
    "raps": ["n_envs:1", "option_steps:5", "learning_starts:50", "high_batch_size:16", "policy_kwargs:dict(net_arch=[16])"],
    "dac": ["n_envs:1", "learning_starts:50", "batch_size:16", "buffer_size:2000", "policy_kwargs:dict(net_arch=[16])"],
    "dpo_flat": ["n_envs:1", "learning_starts:50", "segment_length:5", "n_preference_pairs:200", "pairs_per_batch:8"],
    "sac": ["n_envs:1", "learning_starts:50", "batch_size:16", "buffer_size:2000", "policy_kwargs:dict(net_arch=[16])"],
    # The fast maze's entry clones nothing (as DIPPER's): the run clones the task's single demonstration.
    "sac_demo": [
        "n_envs:1",
        "learning_starts:50",
        "batch_size:16",
        "buffer_size:2000",
        "policy_kwargs:dict(net_arch=[16])",
        "demo_kwargs:dict(demo_path='auto')",
    ],
}


def zoo(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "sb3_dipper.zoo", *args], cwd=cwd, capture_output=True, text=True, timeout=600
    )


@pytest.mark.parametrize("path", YAML_FILES, ids=lambda path: path.stem)
def test_every_yaml_entry_names_only_constructor_keywords(path):
    algorithm = ALGORITHMS[path.stem]
    accepted = set(inspect.signature(algorithm.__init__).parameters)
    entries = yaml.safe_load(path.read_text())
    for env_id in entries:
        entry = load_entry(path.stem, env_id)
        unknown = set(entry) - accepted - set(ZOO_KEYS)
        assert not unknown, f"{path.name}[{env_id}] has keys {unknown} that {algorithm.__name__} does not take"
        assert entry["monitor_kwargs"] == dict(info_keywords=("is_success",))


@pytest.mark.parametrize("path", YAML_FILES, ids=lambda path: path.stem)
def test_every_algorithm_has_the_fast_env_the_paper_tasks_and_a_default(path):
    """Both sets: the CPU profiles here and the paper scale in hyperparams/paper/ (their sizes: test_profiles.py)."""
    assert {ENV_ID, "default", *PAPER_TASKS} <= set(yaml.safe_load(path.read_text()))
    assert {"default", *PAPER_TASKS} <= set(yaml.safe_load((path.parent / "paper" / path.name).read_text()))


def test_every_zoo_algorithm_has_a_hyperparameter_file():
    assert set(ZOO_ALGORITHMS) <= {path.stem for path in YAML_FILES}


@pytest.mark.parametrize(("argv", "exit_code"), [([], 2), (["--help"], 0), (["-h"], 0), (["trian"], 2)])
def test_the_command_line_prints_its_usage(argv, exit_code, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["sb3-dipper-zoo", *argv])
    with pytest.raises(SystemExit) as exited:
        main()
    assert exited.value.code == exit_code
    printed = capsys.readouterr()
    assert "usage: sb3-dipper-zoo" in printed.out + printed.err
    if exit_code == 0 or not argv:
        assert all(command in printed.out for command in ("train", "enjoy", "record_video", "COMMAND --help"))


def test_train_help_lists_rl_zoos_flags_and_ours_each_with_its_help(tmp_path):
    # --resume names no paused run: a help request is answered before our flags are checked.
    result = zoo("train", "--resume", "nowhere", "-h", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    help_text = " ".join(result.stdout.split())  # argparse wraps lines at the terminal's width
    assert "usage: sb3-dipper-zoo train" in help_text and "--n-timesteps" in help_text and "dipper" in help_text
    ours = [action for action in run_control_parser()._actions if action.option_strings]
    assert {flag for action in ours for flag in action.option_strings} == {"--pause-after-minutes", "--resume", "--label-page"}
    for action in ours:
        assert action.help and f"{action.option_strings[0]} {action.metavar} {action.help}" in help_text
    assert help_text.index("--n-timesteps") < help_text.index("sb3-dipper-zoo train's own flags")


@pytest.mark.parametrize("algo_flag", [["--algo", "dipper"], ["--algo=dipper"], ["--alg", "dipper"]])
def test_train_reads_our_hyperparameter_file_whichever_way_algo_is_spelt(algo_flag):
    # FetchReach-v4 has no entry of its own: rl-zoo3 falls back to the file's `default` entry, no copy is written.
    argv = zoo_argv("train", [*algo_flag, "--env", "FetchReach-v4"])
    assert argv[-2:] == ["--conf-file", str(hyperparams_dir() / "dipper.yml")]
    assert "default" in yaml.safe_load((hyperparams_dir() / "dipper.yml").read_text())


def test_a_conf_file_the_user_gives_is_kept():
    for flag in (["-conf", "mine.yml"], ["--conf-file=mine.yml"]):
        argv = zoo_argv("train", ["--algo", "dipper", "--env", ENV_ID, *flag])
        assert "--conf-file" not in argv[-2:] and argv[-1].endswith("mine.yml")
    assert zoo_argv("enjoy", ["--algo", "dipper", "--env", ENV_ID]) == ["--algo", "dipper", "--env", ENV_ID]
    plot_flags = ["--algo", "dipper", "-e", "sb3_dipper:A-v0", "sb3_dipper:B-v0", "-f", "logs"]
    assert zoo_argv("plot_train", plot_flags) == plot_flags


def test_a_module_prefixed_env_id_is_imported_and_passed_on_plain():
    argv = zoo_argv("enjoy", ["--algo", "dipper", "--env=sb3_dipper:PointMazeFourRooms-v0", "-f", "logs"])
    assert argv[-2:] == ["--env", ENV_ID]
    with pytest.raises(ModuleNotFoundError, match="--env no_such_module:X-v0"):
        zoo_argv("train", ["--algo", "dipper", "--env", "no_such_module:X-v0"])


def test_runs_sharing_a_log_folder_each_claim_their_own_run_folder(tmp_path):
    (tmp_path / "dipper" / f"{ENV_ID}_1").mkdir(parents=True)
    log_path = str(tmp_path / "dipper")
    claimed = [claim_run_folder(log_path, ENV_ID, run_id=1) for _ in range(2)]
    assert claimed == [str(tmp_path / "dipper" / f"{ENV_ID}_{run_id}") for run_id in (2, 3)]
    assert all(Path(path).is_dir() for path in claimed)


def test_rl_zoo_train_claims_each_run_folder_when_it_creates_it(tmp_path):
    # Two experiment managers built before either creates its folder (two workers started together) pick the same
    # run id; the one register() installs in rl-zoo3's train still gives each its own folder.
    script = f"""
import argparse, rl_zoo3.train
from sb3_dipper.zoo import register
register()
managers = [rl_zoo3.train.ExperimentManager(argparse.Namespace(), "dipper", "{ENV_ID}", "logs") for _ in range(2)]
for manager in managers:
    manager.create_log_folder()
print(*(manager.params_path for manager in managers))
"""
    result = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    params_paths = result.stdout.split()[-2:]
    assert params_paths == [f"logs/dipper/{ENV_ID}_{run_id}/{ENV_ID}" for run_id in (1, 2)]
    assert all((tmp_path / path).is_dir() for path in params_paths)


def test_progress_csv_is_never_shared_between_runs(tmp_path):
    env = short_maze(monitor_dir=str(tmp_path))
    (tmp_path / "progress.csv").write_text("another run's rows\n")
    with pytest.raises(FileExistsError, match=r"progress\.csv already exists"):
        tiny_model(HIER, env).learn(10, callback=CSVProgressCallback())
    assert (tmp_path / "progress.csv").read_text() == "another run's rows\n"
    env.close()


def test_progress_csv_has_the_columns_and_cells_of_sb3s_csv_writer(tmp_path):
    """plot.py, --resume and the committed CSVs read progress.csv as SB3's CSVOutputFormat wrote it: the same columns
    and cells (strings quoted, a key a record lacks left empty), though new keys no longer rewrite the file in place."""
    records = [
        {STEPS_KEY: 100, "rollout/ep_rew_mean": -17.571428571428573, "time/fps": 51},
        {STEPS_KEY: 200, "rollout/ep_rew_mean": -1e-7, "train/actor_loss": 0.5, "train/n_updates": 3, "time/fps": 50},
        {STEPS_KEY: 200, "eval/mean_reward": -3.0, "eval/note": 'say "hi", twice', "eval/frames": "x" * 3},
        {STEPS_KEY: 300, "rollout/ep_rew_mean": float("nan"), "train/n_updates": 7, "train/not_for_csv": 1.0},
        {STEPS_KEY: 400, "eval/mean_reward": None, "rollout/low_value": np.float32(-0.25)},
    ]
    excluded = {"train/not_for_csv": ("csv",), "time/fps": ("tensorboard",)}
    sb3_writer = CSVOutputFormat(str(tmp_path / "sb3.csv"))
    writer = AtomicCSVOutputFormat(tmp_path / "progress.csv")
    for record in records:
        sb3_writer.write(record, excluded)
        writer.write(record, excluded)
    sb3_writer.close()

    def cells(name: str) -> list[dict[str, str]]:
        with open(tmp_path / name, newline="") as file:
            return list(csv.DictReader(file))

    assert cells("progress.csv") == cells("sb3.csv") and len(cells("sb3.csv")) == len(records)
    assert '"say ""hi"", twice"' in (tmp_path / "progress.csv").read_text()
    sb3_table = pd.read_csv(tmp_path / "sb3.csv")
    pd.testing.assert_frame_equal(read_progress(tmp_path / "progress.csv")[sb3_table.columns], sb3_table)


def test_a_run_killed_while_progress_csv_gets_new_columns_leaves_the_file_whole(tmp_path, monkeypatch):
    """SB3's CSV writer rewrote progress.csv in place whenever a key appeared: a run killed meanwhile left rows cut and
    spliced (a mean reward of 7e9, a row lost), which --resume and plot.py took as they were."""
    env = short_maze(monitor_dir=str(tmp_path))
    # The evaluation's record comes first, at step 50; the training record at step 80 brings new keys.
    evaluation = EvalCallback(short_maze(), eval_freq=50, n_eval_episodes=1)
    progress = tmp_path / "progress.csv"
    fsync = os.fsync
    files_before_a_rewrite = []

    def killed_at_the_second_rewrite(descriptor):
        files_before_a_rewrite.append(progress.read_text())
        if len(files_before_a_rewrite) == 2:
            raise Killed
        fsync(descriptor)

    monkeypatch.setattr(os, "fsync", killed_at_the_second_rewrite)
    with pytest.raises(Killed):
        tiny_model(HIER, env).learn(100, callback=[CSVProgressCallback(), evaluation])
    monkeypatch.undo()
    assert progress.read_text() == files_before_a_rewrite[-1]
    assert sorted(path.name for path in tmp_path.iterdir()) == ["0.monitor.csv", "progress.csv"]  # no temporary file
    logged = read_progress(progress)
    assert logged[STEPS_KEY].tolist() == [50] and "eval/mean_reward" in logged
    env.close()
    evaluation.eval_env.close()


def test_training_in_chunks_appends_to_the_models_own_progress_csv(tmp_path):
    """A second learn(..., reset_num_timesteps=False) of the same model was refused as another run's."""
    env = short_maze(monitor_dir=str(tmp_path))
    model = tiny_model(HIER, env)
    model.learn(100, callback=CSVProgressCallback())
    first = read_progress(tmp_path / "progress.csv")[STEPS_KEY].tolist()
    model.learn(100, callback=CSVProgressCallback(), reset_num_timesteps=False)
    both = read_progress(tmp_path / "progress.csv")[STEPS_KEY].tolist()
    assert first and both[: len(first)] == first and len(both) > len(first) and min(both[len(first) :]) > 100

    with pytest.raises(FileExistsError, match=r"restarts the step count \(reset_num_timesteps=True\)"):
        model.learn(100, callback=CSVProgressCallback())
    with pytest.raises(FileExistsError, match="another run logs to the same folder"):
        tiny_model(HIER, env).learn(100, callback=CSVProgressCallback(), reset_num_timesteps=False)
    assert read_progress(tmp_path / "progress.csv")[STEPS_KEY].tolist() == both
    env.close()


def test_a_run_with_subprocess_envs_writes_progress_csv_to_the_folder_given(tmp_path):
    """Under SubprocVecEnv (rl-zoo3's --vec-env subproc) the callback asked a worker for its Monitor's open file, which
    cannot be pickled: training failed at its start with a bare EOFError."""
    env = short_maze(n_envs=2, monitor_dir=str(tmp_path), vec_env_cls=SubprocVecEnv)
    model = tiny_model(HIER, env)
    with pytest.raises(ValueError, match=r"a SubprocVecEnv .* CSVProgressCallback\(folder=\.\.\.\)"):
        model.learn(200, callback=CSVProgressCallback())
    model.learn(200, callback=CSVProgressCallback(folder=tmp_path))
    assert read_progress(tmp_path / "progress.csv")[STEPS_KEY].max() > 0
    env.close()


def test_train_with_subprocess_envs_logs_progress_csv(tmp_path):
    """Every YAML of ours names CSVProgressCallback: `--vec-env subproc` failed at the start with a bare EOFError."""
    params = [*(param for param in TINY_PARAMS["hier"] if not param.startswith("n_envs:")), "n_envs:2"]
    trained = zoo(
        "train", "--algo", "hier", "--env", f"sb3_dipper:{ENV_ID}", "--vec-env", "subproc", "-n", "300", "--seed", "0",
        "-f", "logs", "--eval-freq", "-1", "--env-kwargs", "max_episode_steps:50", "-params", *params, cwd=tmp_path,
    )  # fmt: skip
    assert trained.returncode == 0, trained.stderr[-3000:]
    assert read_progress(tmp_path / "logs" / "hier" / f"{ENV_ID}_1" / "progress.csv")[STEPS_KEY].max() > 0


class Killed(Exception):
    """A kill of the training process, as the test raises it."""


def test_a_run_killed_while_it_writes_its_evaluations_keeps_the_previous_record(tmp_path, monkeypatch):
    """SB3's EvalCallback rewrote evaluations.npz in place at every evaluation: a kill meanwhile left it cut short, and
    every evaluation so far with it (plot.py and the benchmark report then failed on a BadZipFile naming no file)."""
    model = SAC("MlpPolicy", "Pendulum-v1", learning_starts=1000, buffer_size=1000, policy_kwargs=dict(net_arch=[16]))
    eval_env = Monitor(gym.make("Pendulum-v1", max_episode_steps=10))
    evaluation = AtomicEvalCallback(eval_env, eval_freq=5, log_path=str(tmp_path))
    model.learn(5, callback=evaluation)
    record = tmp_path / "evaluations.npz"
    with np.load(record) as data:  # SB3's record: its keys, read by numpy as SB3's and rl-zoo3's tools read it
        assert sorted(data.files) == ["ep_lengths", "results", "timesteps"] and data["timesteps"].tolist() == [5]
    first = record.read_bytes()
    savez = np.savez

    def killed_while_writing(file, **arrays):
        savez(file, **arrays)
        written = npz_path(file)
        written.write_bytes(written.read_bytes()[: written.stat().st_size // 2])
        raise Killed

    monkeypatch.setattr(np, "savez", killed_while_writing)
    with pytest.raises(Killed):
        model.learn(5, callback=evaluation, reset_num_timesteps=False)
    assert record.read_bytes() == first
    assert [path.name for path in tmp_path.iterdir()] == ["evaluations.npz"]  # no temporary file left behind


def test_rl_zoo_train_evaluates_with_the_callback_that_writes_the_record_whole(tmp_path):
    script = """
import argparse, rl_zoo3.exp_manager, rl_zoo3.train
from stable_baselines3.common.callbacks import EvalCallback
from sb3_dipper.zoo import register
register()
manager = rl_zoo3.train.ExperimentManager(argparse.Namespace(), "sac", "Pendulum-v1", "logs", eval_freq=100, verbose=0)
manager.create_log_folder()
manager.create_callbacks()
print(*(type(callback).__name__ for callback in manager.callbacks), rl_zoo3.exp_manager.EvalCallback is EvalCallback)
"""
    result = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.split("\n")[-2] == "AtomicEvalCallback True"  # rl-zoo3's own name is left as it was


def test_dipper_nov_is_tuned_without_the_lower_value_term():
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    for _ in range(20):
        trial = study.ask()
        assert SAMPLERS["dipper_nov"](trial, 2, 1, {})["value_reg_coef"] == 0.0
        assert "value_reg_coef" not in trial.params
    # A stored trial, even one of a DIPPER study, trains DIPPER-No-V with lambda = 0.
    assert keep_params_without_value_term({"value_reg_coef": 0.1, "beta": 0.2}) == {"value_reg_coef": 0.0, "beta": 0.2}


def test_a_dipper_trial_samples_nll_coef_into_switch_kwargs_and_a_stored_one_converts_alike():
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    for algo in ("dipper", "dipper_paper", "dipper_nov"):
        trial = study.ask()
        sampled = SAMPLERS[algo](trial, 2, 1, {})
        assert sampled["switch_kwargs"] == {"nll_coef": trial.params["nll_coef"]} and "nll_coef" not in sampled
        # A stored trial (before switch_kwargs too: Optuna's name is the same) converts to what was sampled.
        assert CONVERTERS[algo](trial.params) == sampled, algo


def test_a_trial_changes_only_the_switches_it_samples_and_keeps_the_entrys_others(tmp_path):
    """rl-zoo3 sets a trial's dict over the entry's whole dict; the installed manager completes it by the entry's keys,
    for a sampled trial (-optimize) and a stored one (--trial-id) alike."""
    script = f"""
import argparse, optuna, rl_zoo3.train
from rl_zoo3.exp_manager import ExperimentManager
from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER
from sb3_dipper.zoo import SAMPLERS, hyperparams_dir, register
from sb3_dipper.zoo.run_config import load_entry
register()
trial = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0)).ask()
# rl-zoo3's own steps, as they call the sampler and the converter.
ExperimentManager.hyperparameters_optimization = lambda self: setattr(
    self, "sampled", HYPERPARAMS_SAMPLER[self.algo](trial, 2, 1, {{}})
)
ExperimentManager.load_trial = lambda self, *args, **kwargs: HYPERPARAMS_CONVERTER[self.algo]({{"nll_coef": 0.5, "beta": 0.2}})
config = str(hyperparams_dir() / "dipper.yml")
manager = rl_zoo3.train.ExperimentManager(argparse.Namespace(), "dipper", "{ENV_ID}", "logs", config=config)
entry = load_entry("dipper", "{ENV_ID}")
manager._hyperparams = entry
manager.hyperparameters_optimization()
assert HYPERPARAMS_SAMPLER["dipper"] is SAMPLERS["dipper"]
assert manager.sampled["switch_kwargs"] == {{**entry["switch_kwargs"], "nll_coef": trial.params["nll_coef"]}}
stored = manager.load_trial("storage", "s", 1)
assert stored == {{"switch_kwargs": {{**entry["switch_kwargs"], "nll_coef": 0.5}}, "beta": 0.2}}, stored
print(sorted(entry["switch_kwargs"]))
"""
    result = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.split("\n")[-2] == "['hindsight_actions', 'nll_coef', 'truncate_at_goal']"


def test_train_on_an_upstream_goal_env_without_an_entry_of_its_own(tmp_path):
    trained = zoo(
        "train", "--algo=dipper", "--env=gymnasium_robotics:FetchReach-v4", "-n", "200", "--seed", "0", "-f", "logs",
        "--eval-freq", "-1", "-params", *TINY_PARAMS["dipper"], cwd=tmp_path,
    )  # fmt: skip
    assert trained.returncode == 0, trained.stderr[-3000:]
    assert f"Loading hyperparameters from: {hyperparams_dir() / 'dipper.yml'}" in trained.stdout
    assert "Using 'default' hyperparameters" in trained.stdout
    run_dir = tmp_path / "logs" / "dipper" / "FetchReach-v4_1"
    assert (run_dir / "FetchReach-v4.zip").exists() and (run_dir / "progress.csv").exists()


# DIPPER's pair runs by default; the other algorithms' (~12 s each) under `make test-slow`: in-process, tests/test_run.py
# and tests/test_save_load.py train, save, load and predict every algorithm.
@pytest.mark.parametrize(
    "algo", [algo if algo == "dipper" else pytest.param(algo, marks=pytest.mark.slow) for algo in sorted(TINY_PARAMS)]
)
def test_train_then_enjoy_in_subprocesses(algo, tmp_path):
    trained = zoo(
        "train", "--algo", algo, "--env", ENV_ID, "-n", "300", "--seed", "0", "-f", "logs", "--eval-freq", "-1",
        "--env-kwargs", "max_episode_steps:50", "-params", *TINY_PARAMS[algo], cwd=tmp_path,
    )  # fmt: skip
    assert trained.returncode == 0, trained.stderr[-3000:]
    run_dir = tmp_path / "logs" / algo / f"{ENV_ID}_1"
    assert (run_dir / f"{ENV_ID}.zip").exists()

    enjoyed = zoo(
        "enjoy", "--algo", algo, "--env", ENV_ID, "-f", "logs", "--exp-id", "1", "-n", "120", "--no-render",
        "--env-kwargs", "max_episode_steps:50", cwd=tmp_path,
    )  # fmt: skip
    assert enjoyed.returncode == 0, enjoyed.stderr[-3000:]
    assert "Success rate:" in enjoyed.stdout


def test_a_hyperparameter_typo_names_the_keyword(tmp_path):
    result = zoo("train", "--algo", "dipper", "--env", ENV_ID, "-n", "10", "-f", "logs", "-params", "betta:0.1", cwd=tmp_path)
    assert result.returncode != 0
    assert "DIPPER got an unexpected keyword argument 'betta'; did you mean 'beta'?" in result.stderr


def test_an_unknown_algorithm_is_refused(tmp_path):
    result = zoo("train", "--algo", "dipperr", "--env", ENV_ID, "-n", "10", cwd=tmp_path)
    assert result.returncode != 0
    assert "dipperr" in result.stderr and "dipper" in result.stderr


def optimize_args(algo: str, storage: str, log_folder: str, n_trials: int = 1) -> list[str]:
    """One tuning worker: random sampler, no pruning, one evaluation of 2 episodes after 300 steps per trial."""
    return [
        "train", "--algo", algo, "--env", ENV_ID, "-f", log_folder, "-optimize", "--storage", storage, "--study-name", "s",
        "--n-trials", str(n_trials), "--n-jobs", "1", "-n", "300", "--eval-episodes", "2", "--n-evaluations", "1",
        "--sampler", "random", "--pruner", "none", "--no-optim-plots", "--env-kwargs", "max_episode_steps:50",
        "-params", *TINY_PARAMS[algo],
    ]  # fmt: skip


def test_two_tuning_workers_share_a_journal_file_study(tmp_path):
    # Each worker has its own log folder: rl-zoo3 names a tuning report after the second it is written in.
    command = [sys.executable, "-m", "sb3_dipper.zoo"]
    storage_path = str(tmp_path / "study.log")
    workers = [
        subprocess.Popen([*command, *optimize_args("dipper", storage_path, f"worker{i}")], cwd=tmp_path, text=True,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        for i in range(2)
    ]  # fmt: skip
    outputs = [worker.communicate(timeout=600) for worker in workers]
    for worker, (_, stderr) in zip(workers, outputs, strict=True):
        assert worker.returncode == 0, stderr[-3000:]

    storage = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(storage_path))
    study = optuna.load_study(study_name="s", storage=storage)
    assert [trial.state for trial in study.trials] == [TrialState.COMPLETE] * 2
    # Optuna numbers trials across the whole study: each worker ran one of the two.
    finished = [{number for number in (0, 1) if f"Trial {number} finished" in stderr} for _, stderr in outputs]
    assert sorted(map(sorted, finished)) == [[0], [1]]
    assert {"beta", "option_steps"} <= set(study.trials[0].params)  # DIPPER's own search space, from register()


def test_tuning_with_an_sqlite_study_then_training_with_a_trial(tmp_path):
    tuned = zoo(*optimize_args("hier", f"sqlite:///{tmp_path / 'study.db'}", "logs", n_trials=2), cwd=tmp_path)
    assert tuned.returncode == 0, tuned.stderr[-3000:]
    study = optuna.load_study(study_name="s", storage=f"sqlite:///{tmp_path / 'study.db'}")
    assert [trial.state for trial in study.trials] == [TrialState.COMPLETE] * 2
    assert list((tmp_path / "logs" / "hier").glob("report_*.csv"))

    # rl-zoo3 loads a stored trial's parameters only for a truthy --trial-id, so trial 0 cannot be chosen this way.
    trained = zoo(
        "train", "--algo", "hier", "--env", ENV_ID, "-n", "100", "-f", "logs", "--eval-freq", "-1",
        "--storage", f"sqlite:///{tmp_path / 'study.db'}", "--study-name", "s", "--trial-id", "1",
        "--env-kwargs", "max_episode_steps:50", "-params", *TINY_PARAMS["hier"], cwd=tmp_path,
    )  # fmt: skip
    assert trained.returncode == 0, trained.stderr[-3000:]
    config = yaml.unsafe_load((tmp_path / "logs" / "hier" / f"{ENV_ID}_2" / ENV_ID / "config.yml").read_text())
    assert dict(config)["learning_rate"] == study.trials[1].params["learning_rate"]


@pytest.mark.parametrize("algo", sorted(SAMPLERS))
def test_every_sampler_suggests_only_constructor_keywords(algo):
    accepted = set(inspect.signature(ZOO_ALGORITHMS[algo].__init__).parameters)
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    for _ in range(20):
        params = SAMPLERS[algo](study.ask(), 2, 1, {"using_her_replay_buffer": False, "her_kwargs": {}})
        assert set(params) <= accepted, f"{algo}'s sampler suggests {set(params) - accepted}"


def test_a_hierarchical_run_logs_its_metrics_to_csv_and_records_a_video(tmp_path):
    trained = zoo(
        "train", "--algo", "hier", "--env", ENV_ID, "-n", "300", "--seed", "0", "-f", "logs", "--eval-freq", "-1",
        "--env-kwargs", "max_episode_steps:50", "-params", *TINY_PARAMS["hier"], cwd=tmp_path,
    )  # fmt: skip
    assert trained.returncode == 0, trained.stderr[-3000:]
    run_dir = tmp_path / "logs" / "hier" / f"{ENV_ID}_1"
    header = (run_dir / "progress.csv").read_text().splitlines()[0].split(",")
    assert {"rollout/subgoal_distance", "rollout/low_value", "rollout/success_rate"} <= set(header)

    recorded = zoo(
        "record_video", "--algo", "hier", "--env", ENV_ID, "-f", "logs", "--exp-id", "1", "-n", "60",
        "--env-kwargs", "max_episode_steps:50", cwd=tmp_path,
    )  # fmt: skip
    assert recorded.returncode == 0, recorded.stderr[-3000:]
    assert list((run_dir / "videos").glob("*.mp4"))
