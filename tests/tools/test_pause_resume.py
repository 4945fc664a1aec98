"""Runs longer than a session: ``sb3-dipper-zoo train --pause-after-minutes`` leaves a resume checkpoint, ``--resume``
continues the run in its folder to its whole budget, and ``benchmark.py learning`` does both by rerunning a command."""

import json
import os
import re
import subprocess
import sys
import zipfile
from collections import OrderedDict
from pathlib import Path

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest
import rl_zoo3
import torch as th
import yaml
from stable_baselines3 import SAC
from stable_baselines3.common.callbacks import CheckpointCallback, EvalCallback

from sb3_dipper import DIPPER, HIER
from sb3_dipper.zoo import (
    RESUME_FOLDER,
    RESUME_MODEL,
    PauseCheckpointCallback,
    check_resume_checkpoint,
    check_resumed_evaluations,
    check_resumed_hyperparameters,
    continue_evaluations,
    resumed_n_timesteps,
    run_env_folder,
    saved_steps,
    set_aside_part,
    split_run_control,
)
from sb3_dipper.zoo import main as zoo_main
from tests.conftest import short_maze, tiny_model
from tests.test_files import truncate
from tests.tools.test_benchmark import ENV_ID, learning_command, run_folder


@pytest.mark.parametrize("algo", ["hier", "sac"])
def test_a_paused_run_resumes_in_its_folder_to_its_whole_budget(algo, tmp_path):
    out = tmp_path / "runs"
    command = learning_command(out, "--algos", algo, "--seeds", "0", "--workers", "1", "--save-freq", "150")
    paused = subprocess.run([*command, "--pause-after-minutes", "0"], capture_output=True, text=True, timeout=300)
    assert paused.returncode == 0, paused.stderr[-3000:]
    run = run_folder(out, algo, 0)
    assert "seed 0: paused after 1 of 300 steps; the same command resumes it" in paused.stdout
    assert (run / RESUME_FOLDER / RESUME_MODEL).is_file() and not (run / "result.json").exists()

    resumed = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "1 runs to do, 0 already finished" in resumed.stdout
    # The same folder, trained to the end: the step count went on, the evaluations are on the run's grid.
    assert sorted(path.name for path in run.parent.iterdir()) == [f"{ENV_ID}.log", f"{ENV_ID}_1"]
    with zipfile.ZipFile(run / f"{ENV_ID}.zip") as archive:
        data = json.loads(archive.read("data"))
    assert data["num_timesteps"] >= 300 and data["_total_timesteps"] == 300
    with np.load(run / "evaluations.npz") as evaluations:
        assert list(evaluations["timesteps"]) == [150, 300]
    assert sorted(path.name for path in run.glob("rl_model_*")) == ["rl_model_150_steps.zip", "rl_model_300_steps.zip"]
    result = json.loads((run / "result.json").read_text())
    assert result["seconds"] >= json.loads((run / "parts.json").read_text())["seconds"] > 0
    assert not (run / RESUME_FOLDER).exists()  # nothing is left to resume
    # The paused part's logs are set aside; the resumed part logged its own.
    assert (run / "part_1" / "0.monitor.csv").exists() and (run / "0.monitor.csv").exists()
    if algo == "hier":
        assert (run / "part_1" / "progress.csv").exists() and (run / "progress.csv").exists()


def fake_checkpoint(run: Path, num_timesteps: int) -> None:
    (run / RESUME_FOLDER).mkdir(parents=True)
    with zipfile.ZipFile(run / RESUME_FOLDER / RESUME_MODEL, "w") as archive:
        archive.writestr("data", json.dumps({"num_timesteps": num_timesteps}))


def test_the_resumed_evaluation_continues_the_recorded_one(tmp_path):
    """Evaluations after the checkpoint (made by a part killed before its next pause) are dropped: they are made again."""
    np.savez(
        tmp_path / "evaluations.npz",
        timesteps=np.array([100, 200, 300]),
        results=np.array([[-50.0, -40.0], [-10.0, -20.0], [0.0, 0.0]]),
        ep_lengths=np.full((3, 2), 50),
        successes=np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]),
    )
    evaluation = EvalCallback(gym.make("Pendulum-v1"), eval_freq=50)
    checkpoint = CheckpointCallback(save_freq=50, save_path=str(tmp_path))
    continue_evaluations([evaluation, checkpoint], num_timesteps=250, n_envs=2, run_folder=tmp_path)
    assert evaluation.n_calls == checkpoint.n_calls == 125
    assert evaluation.evaluations_timesteps == [100, 200]
    assert evaluation.evaluations_results == [[-50.0, -40.0], [-10.0, -20.0]]
    assert evaluation.evaluations_successes == [[0.0, 0.0], [1.0, 0.0]]
    assert evaluation.best_mean_reward == -15.0


def test_setting_a_part_aside_keeps_only_the_steps_of_the_checkpoint(tmp_path):
    fake_checkpoint(tmp_path, num_timesteps=200)
    checkpoint_time = 1_000_000.0
    os.utime(tmp_path / RESUME_FOLDER / RESUME_MODEL, (checkpoint_time, checkpoint_time))
    # Episodes that ended 90 s and 10 s before the checkpoint was written, and one 100 s after (trained again).
    header = '#{"t_start": 999900.0, "env_id": "FetchPushFixed-v0"}'
    (tmp_path / "0.monitor.csv").write_text(
        f"{header}\nr,l,t,is_success\n-50.0,50,10.0,0.0\n-3.0,50,90.0,1.0\n-50.0,50,200.0,0.0\n"
    )
    (tmp_path / "1.monitor.csv").write_text(f"{header}\nr,l,t,is_success\n")  # no episode finished yet
    pd.DataFrame({"time/total_timesteps": [100, 200, 300], "rollout/low_value": [-1.0, -2.0, -3.0]}).to_csv(
        tmp_path / "progress.csv", index=False
    )
    set_aside_part(tmp_path)
    assert not (tmp_path / "progress.csv").exists() and not (tmp_path / "0.monitor.csv").exists()
    assert pd.read_csv(tmp_path / "part_1" / "progress.csv")["time/total_timesteps"].tolist() == [100, 200]
    monitor = (tmp_path / "part_1" / "0.monitor.csv").read_text().splitlines()
    assert monitor[0] == header and pd.read_csv(tmp_path / "part_1" / "0.monitor.csv", skiprows=1)["t"].tolist() == [10, 90]
    assert (tmp_path / "part_1" / "1.monitor.csv").read_text() == f"{header}\nr,l,t,is_success\n"
    set_aside_part(tmp_path)  # nothing logged since: no empty part
    assert sorted(path.name for path in tmp_path.iterdir()) == ["part_1", RESUME_FOLDER]


@pytest.mark.parametrize(
    "rows, problem",
    [
        # Killed while SB3's CSV logger rewrote the file for train/actor_loss: the rows after the cut lack its column.
        (["100,-1.0,", "200,-2.0,0.5", "-3.0,300", "-4.0,400"], "line 4 has 2 fields, the header 3"),
        (["100,-1.0,", "300,-3.0,0.5", "200,-2.0,0.5"], "line 4 logs time/total_timesteps 200 after 300"),
    ],
)
def test_a_damaged_progress_csv_is_refused_before_the_part_is_set_aside(tmp_path, rows, problem):
    """A progress.csv cut and spliced by a run killed while SB3 rewrote it was set aside as the part's record, its wrong
    rows included."""
    fake_checkpoint(tmp_path, num_timesteps=400)
    progress = tmp_path / "progress.csv"
    progress.write_text("\n".join(["time/total_timesteps,rollout/low_value,train/actor_loss", *rows]) + "\n")
    (tmp_path / "0.monitor.csv").write_text('#{"t_start": 0.0}\nr,l,t\n')
    damaged = progress.read_text()
    with pytest.raises(ValueError, match=rf"{re.escape(str(progress))}: {problem}.* delete line 4 and the lines after"):
        set_aside_part(tmp_path)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["0.monitor.csv", "progress.csv", RESUME_FOLDER]
    assert progress.read_text() == damaged


def test_the_pause_and_resume_flags_are_ours_and_checked(tmp_path):
    control, rest = split_run_control(["--algo", "sac", "--pause-after-minutes", "80", "-n", "10"])
    assert control.pause_after_minutes == 80.0 and control.resume is None and rest == ["--algo", "sac", "-n", "10"]
    with pytest.raises(ValueError, match="--pause-after-minutes must be >= 0"):
        split_run_control(["--pause-after-minutes", "-1"])
    with pytest.raises(FileNotFoundError, match=f"--resume {tmp_path}: no resume checkpoint"):
        split_run_control(["--resume", str(tmp_path)])
    fake_checkpoint(tmp_path, num_timesteps=10)
    assert split_run_control(["--resume", str(tmp_path)])[0].resume == tmp_path


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--pause-after-minutes", "-1"], "sb3-dipper-zoo train: error: --pause-after-minutes must be >= 0 minutes"),
        (["--resume", "nowhere"], "sb3-dipper-zoo train: error: --resume nowhere: no resume checkpoint"),
        (["--label-page", "localhost:port"], "sb3-dipper-zoo train: error: --label-page"),
    ],
)
def test_the_command_reports_a_bad_flag_as_a_usage_error(monkeypatch, capsys, flags, message):
    """One line naming the flag and exit status 2, as argparse reports its own errors, not a traceback."""
    monkeypatch.setattr(sys, "argv", ["sb3-dipper-zoo", "train", "--algo", "sac", *flags])
    with pytest.raises(SystemExit) as exited:
        zoo_main()
    assert exited.value.code == 2
    error = capsys.readouterr().err
    assert error.startswith(message) and error.count("\n") == 1


def test_an_algorithm_without_a_replay_buffer_cannot_pause(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "sb3_dipper.zoo", "train", "--algo", "ppo", "--env", "Pendulum-v1", "-n", "64",
         "-f", str(tmp_path), "--pause-after-minutes", "0", "-params", "n_steps:32", "batch_size:32"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert result.returncode != 0
    assert "pausing and resuming is for off-policy algorithms" in result.stderr


def stored_steps(buffer) -> int:
    return (buffer.buffer_size if buffer.full else buffer.pos) * buffer.n_envs


@pytest.mark.parametrize("model_class", [SAC, HIER, DIPPER])
def test_the_pause_checkpoint_stores_every_step_it_counts(model_class, tmp_path):
    """The step whose on_step pauses training is counted: the checkpoint's buffers hold it too."""
    env = short_maze(n_envs=2)
    if model_class is SAC:
        model = SAC("MultiInputPolicy", env, learning_starts=20, buffer_size=500, policy_kwargs=dict(net_arch=[16]))
    else:
        model = tiny_model(model_class, env)
    pause = PauseCheckpointCallback(0.0, tmp_path, "env")
    pause.seconds = 0.5  # some steps in, mid-option
    model.learn(100_000, callback=pause)
    assert pause.paused and 0 < model.num_timesteps < 100_000
    saved = model_class.load(tmp_path / RESUME_FOLDER / RESUME_MODEL, env=env)
    saved.load_replay_buffer(tmp_path / RESUME_FOLDER / "replay_buffer.pkl")
    assert stored_steps(saved.replay_buffer) == saved.num_timesteps == model.num_timesteps
    env.close()


RESUME_SCRIPT = """
import sys
from pathlib import Path

from stable_baselines3 import SAC

from sb3_dipper import zoo

run, *argv = sys.argv[1:]
save = SAC.save


def save_and_record(self, path, *args, **kwargs):
    # The final model: rl-zoo3 saves it as <run>/<env>. Record whether the resume checkpoint was still there.
    if Path(path) == Path(run) / "Pendulum-v1":
        (Path(run) / "checkpoint_at_final_save").write_text(str((Path(run) / "resume").is_dir()))
    save(self, path, *args, **kwargs)


SAC.save = save_and_record
sys.argv = ["sb3-dipper-zoo", "train", *argv]
zoo.main()
"""


# A tiny SAC run of rl-zoo3's own Pendulum entry: the quickest run to pause and resume.
# A normalised run with its own gamma, like the Fetch profiles: rl-zoo3 records the normalize dict with that gamma in
# it, and a resume must still find the hyperparameters it is given the same as the recorded ones.
SAC_PARAMS = ["learning_starts:100", "buffer_size:1000", "batch_size:32", "gamma:0.98", "normalize:dict(norm_obs=True)"]


def pendulum_flags(log_folder: Path) -> list[str]:
    conf = Path(rl_zoo3.__file__).parent / "hyperparams" / "sac.yml"
    flags = ["--algo", "sac", "--env", "Pendulum-v1", "--conf-file", str(conf), "-f", str(log_folder), "--seed", "0"]
    return [*flags, "-n", "300", "--eval-freq", "-1"]


def zoo_train(*flags: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "sb3_dipper.zoo", "train", *flags], capture_output=True, text=True, timeout=300
    )


def paused_pendulum_run(log_folder: Path) -> Path:
    paused = zoo_train(*pendulum_flags(log_folder), "-params", *SAC_PARAMS, "--pause-after-minutes", "0")
    assert paused.returncode == 0, paused.stderr[-3000:]
    run = log_folder / "sac" / "Pendulum-v1_1"
    assert (run / RESUME_FOLDER / RESUME_MODEL).is_file()
    return run


def test_a_resumed_run_keeps_its_checkpoint_until_its_final_model_is_written(tmp_path):
    """Killed between the end of training and the final model, a resumed run must still be resumable."""
    run = paused_pendulum_run(tmp_path)
    flags = [*pendulum_flags(tmp_path), "-params", *SAC_PARAMS]
    resumed = subprocess.run(
        [sys.executable, "-c", RESUME_SCRIPT, str(run), *flags, "--resume", str(run)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert (run / "checkpoint_at_final_save").read_text() == "True"
    assert saved_steps(run / "Pendulum-v1.zip") == (300, 300)
    assert not (run / RESUME_FOLDER).exists()  # removed once the final model was written


def test_a_resumed_run_trains_to_its_own_budget_and_keeps_its_records(tmp_path):
    """The reported case: resumed with a smaller -n, a run trained 0 steps, called itself finished and removed its
    resume checkpoint; resumed without -n, it trained to the YAML budget; either way rl-zoo3 rewrote its args.yml and
    config.yml in place. Another -n is refused before anything changes; without -n the run trains to its own."""
    run = paused_pendulum_run(tmp_path)
    flags = [*pendulum_flags(tmp_path), "-params", *SAC_PARAMS, "--resume", str(run)]
    before = files_under(run)
    smaller = zoo_train(*flags, "-n", "100")  # argparse keeps the last -n
    assert smaller.returncode != 0
    assert f"--resume {run}: -n 100, but the run's budget is 300 primitive steps: it was started with -n 300" in smaller.stderr
    assert "resume it with -n 300 or without -n" in smaller.stderr
    assert files_under(run) == before

    # How the run started: rl-zoo3 would rewrite them in place (args.yml with -n left out).
    records = [Path("Pendulum-v1", name) for name in ("args.yml", "config.yml", "command.txt")]
    without_n = flags[: flags.index("-n")] + flags[flags.index("-n") + 2 :]
    resumed = zoo_train(*without_n)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert saved_steps(run / "Pendulum-v1.zip") == (300, 300)
    assert not (run / RESUME_FOLDER).exists()
    assert {path: (run / path).read_bytes() for path in records} == {path: before[path] for path in records}


def test_the_budget_of_a_resumed_run_is_the_one_it_was_started_with(tmp_path):
    """rl-zoo3 records -n as n_timesteps in args.yml: -1 for a run started without it, which trains to the n_timesteps
    of its hyperparameters (config.yml)."""
    write_config(tmp_path, "Pendulum-v1", {"gamma": 0.98, "n_timesteps": 20000})
    args = tmp_path / "Pendulum-v1" / "args.yml"
    args.write_text(yaml.dump(OrderedDict([("eval_freq", 10000), ("n_timesteps", 100000)])))
    assert resumed_n_timesteps(tmp_path, "Pendulum-v1", -1) == 100000
    assert resumed_n_timesteps(tmp_path, "Pendulum-v1", 100000) == 100000
    for other in (40000, 20000, 200000):
        with pytest.raises(ValueError, match=rf"-n {other}, but the run's budget is 100,000 primitive steps: .* -n 100000"):
            resumed_n_timesteps(tmp_path, "Pendulum-v1", other)

    args.write_text(yaml.dump(OrderedDict([("eval_freq", 10000), ("n_timesteps", -1)])))
    assert resumed_n_timesteps(tmp_path, "Pendulum-v1", -1) == -1
    assert resumed_n_timesteps(tmp_path, "Pendulum-v1", 20000) == 20000
    with pytest.raises(ValueError, match=r"-n 5000, but the run's budget is 20,000 primitive steps: it was started without"):
        resumed_n_timesteps(tmp_path, "Pendulum-v1", 5000)


def files_under(folder: Path) -> dict[Path, bytes]:
    return {path.relative_to(folder): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}


def test_a_run_resumed_with_other_hyperparameters_or_a_damaged_evaluation_record_is_refused(tmp_path):
    """The reported cases: ``--resume RUN -params ...`` trained on with the new values (and saved them), or failed in
    SB3 ("'NoneType' object has no attribute 'load_state_dict'" for ent_coef); a truncated evaluations.npz failed with
    a BadZipFile naming no file. Both are refused before anything in the run folder changes."""
    run = paused_pendulum_run(tmp_path)
    before = files_under(run)
    resume = [*pendulum_flags(tmp_path), "--resume", str(run)]
    refused = zoo_train(*resume, "-params", *SAC_PARAMS, "learning_rate:0.01", "ent_coef:0.05")
    assert refused.returncode != 0
    config = re.escape(str(run / "Pendulum-v1" / "config.yml"))
    assert re.search(rf"the hyperparameters given differ from those the run was started with \({config}\)", refused.stderr)
    assert "  ent_coef: started with (not set), given 0.05\n" in refused.stderr
    assert "  learning_rate: started with 0.001, given 0.01\n" in refused.stderr
    assert "leave out --resume" in refused.stderr
    assert files_under(run) == before
    # A row of 7 evaluation episodes cannot join the record's rows of 5 (numpy failed writing it and left the record
    # holding its timesteps alone).
    other_width = zoo_train(*resume, "-params", *SAC_PARAMS, "--eval-episodes", "7")
    assert other_width.returncode != 0
    assert "--eval-episodes 7 (the run's: 5). A resumed run evaluates as it started" in other_width.stderr
    assert files_under(run) == before
    np.savez(run / "evaluations.npz", timesteps=np.array([100]), results=np.zeros((1, 2)), ep_lengths=np.full((1, 2), 200))
    truncate(run / "evaluations.npz")
    before = files_under(run)
    damaged = zoo_train(*resume, "-params", *SAC_PARAMS)
    assert damaged.returncode != 0
    assert f"Malformed evaluation record {run / 'evaluations.npz'}: not a complete npz archive" in damaged.stderr
    assert files_under(run) == before


def test_a_checkpoint_without_its_buffer_or_statistics_and_another_env_are_refused(tmp_path):
    """rl-zoo3 loads the replay buffer and the normalisation statistics only where they exist: a checkpoint copied
    without them would train on from an empty buffer or new statistics. ``--resume`` with another ``--env`` than the
    run's said that its config.yml was missing."""
    run = tmp_path / "Pendulum-v1_1"
    (run / RESUME_FOLDER / "Pendulum-v1").mkdir(parents=True)
    write_config(run, "Pendulum-v1", {"gamma": 0.98})
    buffer, statistics = run / RESUME_FOLDER / "replay_buffer.pkl", run / RESUME_FOLDER / "Pendulum-v1" / "vecnormalize.pkl"
    buffer.write_bytes(b"buffer")
    check_resume_checkpoint(run, "Pendulum-v1", normalized=False)
    with pytest.raises(FileNotFoundError, match=f"the resume checkpoint lacks {re.escape(str(statistics))}, which pausing"):
        check_resume_checkpoint(run, "Pendulum-v1", normalized=True)
    statistics.write_bytes(b"statistics")
    check_resume_checkpoint(run, "Pendulum-v1", normalized=True)
    buffer.unlink()
    with pytest.raises(FileNotFoundError, match=f"lacks {re.escape(str(buffer))},.* from an empty replay buffer"):
        check_resume_checkpoint(run, "Pendulum-v1", normalized=True)

    assert run_env_folder(run, "Pendulum-v1") == run / "Pendulum-v1"
    with pytest.raises(ValueError, match=r"no folder MountainCar-v0/, .* it trained Pendulum-v1: resume it with that --env"):
        run_env_folder(run, "MountainCar-v0")


def test_the_evaluation_flags_of_a_resumed_run_are_compared_with_its_record(tmp_path):
    (tmp_path / "Pendulum-v1").mkdir()
    record = OrderedDict([("eval_episodes", 20), ("eval_freq", 15000), ("seed", 0)])
    (tmp_path / "Pendulum-v1" / "args.yml").write_text(yaml.dump(record))
    check_resumed_evaluations(tmp_path, "Pendulum-v1", {"eval_freq": 15000, "eval_episodes": 20})
    with pytest.raises(ValueError, match=r"--eval-freq 10000 \(the run's: 15000\), --eval-episodes 5 \(the run's: 20\)"):
        check_resumed_evaluations(tmp_path, "Pendulum-v1", {"eval_freq": 10000, "eval_episodes": 5})
    with pytest.raises(FileNotFoundError, match=r"args.yml is missing: .*start a new run"):
        check_resumed_evaluations(tmp_path, "FetchPush-v4", {"eval_freq": 15000})


def write_config(run: Path, env_name: str, hyperparameters: dict) -> None:
    """A run's config.yml as rl-zoo3 writes it (an OrderedDict dumped by yaml)."""
    (run / env_name).mkdir(parents=True)
    record = OrderedDict((key, hyperparameters[key]) for key in sorted(hyperparameters))
    (run / env_name / "config.yml").write_text(yaml.dump(record))


STARTED = {
    "beta": 0.1,
    "learning_rate": 0.001,
    "n_preference_pairs": 10000,
    "train_freq": (1, "episode"),
    # rl-zoo3 records the dict after the model is built: SB3's SAC has added its use_sde.
    "policy_kwargs": {"net_arch": [16], "activation_fn": th.nn.Tanh, "use_sde": False},
}


def test_the_hyperparameters_of_a_resumed_run_are_compared_with_its_record(tmp_path):
    write_config(tmp_path, "PointMazeFourRooms-v0", STARTED)
    same = {**STARTED, "policy_kwargs": {"net_arch": [16], "activation_fn": th.nn.Tanh}}
    check_resumed_hyperparameters(tmp_path, "PointMazeFourRooms-v0", same)
    changed = {**same, "beta": 0.5, "learning_rate": 0.01, "n_preference_pairs": 500}
    changed["policy_kwargs"] = {"net_arch": [16], "activation_fn": th.nn.ReLU}
    with pytest.raises(ValueError, match="differ from those the run was started with") as error:
        check_resumed_hyperparameters(tmp_path, "PointMazeFourRooms-v0", changed)
    lines = str(error.value).splitlines()
    assert lines[1:5] == [
        "  beta: started with 0.1, given 0.5",
        "  learning_rate: started with 0.001, given 0.01",
        "  n_preference_pairs: started with 10000, given 500",
        "  policy_kwargs: started with {'activation_fn': !!python/name:torch.nn.modules.activation.Tanh, 'net_arch': [16], "
        "'use_sde': False}, given {'activation_fn': !!python/name:torch.nn.modules.activation.ReLU, 'net_arch': [16]}",
    ]
    with pytest.raises(FileNotFoundError, match=r"config.yml is missing: .*start a new run"):
        check_resumed_hyperparameters(tmp_path, "FetchPush-v4", same)


def test_the_gamma_rl_zoo3_writes_into_normalize_is_the_run_s_own(tmp_path):
    write_config(tmp_path, "FetchPush-v4", {"gamma": 0.98, "normalize": {"gamma": 0.98, "norm_obs": True}})
    check_resumed_hyperparameters(tmp_path, "FetchPush-v4", {"gamma": 0.98, "normalize": {"norm_obs": True}})
    with pytest.raises(ValueError) as error:
        check_resumed_hyperparameters(tmp_path, "FetchPush-v4", {"gamma": 0.95, "normalize": {"norm_obs": True}})
    assert str(error.value).splitlines()[1:3] == [
        "  gamma: started with 0.98, given 0.95",
        "  normalize: started with {'gamma': 0.98, 'norm_obs': True}, given {'norm_obs': True}",
    ]


def test_a_run_started_before_demo_kwargs_resumes_with_the_same_settings_in_the_new_form(tmp_path):
    """A run recorded with the lower level's settings as keys of their own (bc_coef: 0.02) is the same experiment as one
    given them in demo_kwargs, and DIPPER's planning: 'subgoal' the same as planner_kwargs: {mode: 'subgoal'}."""
    write_config(tmp_path, "PointMazeFourRooms-v0", {**STARTED, "demo_path": "auto", "bc_coef": 0.02, "planning": "subgoal"})
    new_form = {**STARTED, "demo_kwargs": {"demo_path": "auto", "bc_coef": 0.02}, "planner_kwargs": {"mode": "subgoal"}}
    check_resumed_hyperparameters(tmp_path, "PointMazeFourRooms-v0", new_form)
    with pytest.raises(ValueError, match=r"demo_kwargs: started with \{'demo_path': 'auto', 'bc_coef': 0.02\}, given"):
        check_resumed_hyperparameters(tmp_path, "PointMazeFourRooms-v0", {**new_form, "demo_kwargs": {"demo_path": "auto"}})
