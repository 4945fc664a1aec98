"""zoo_scripts/research/tie_answers.py: how the ties of a trained DIPPER's labels are answered."""

import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from stable_baselines3.common.env_util import make_vec_env

from sb3_dipper import DIPPER
from sb3_dipper.common.trajectories import TrajectoryBuffer
from tests.conftest import tiny_model
from tests.test_preferences import GOAL, OBS_SPACE, add_trajectory, pairs_of
from zoo_scripts.research import tie_answers as tie_answers_script
from zoo_scripts.research.tie_answers import tie_answers

SCRIPT = Path(__file__).resolve().parents[2] / "zoo_scripts" / "research" / "tie_answers.py"


def test_tie_answers_say_how_often_each_answer_prefers_the_trajectory_that_began_nearer():
    buffer = TrajectoryBuffer(capacity=4, max_length=2, observation_space=OBS_SPACE, action_dim=2)
    # GOAL is (3, 0). 0: starts 1 away, ends 1.5 away; 1: starts 6 away, ends 2 away; 2: like 1, its own goal (3, 1).
    add_trajectory(buffer, [(2.0, 1.0), (1.5, 0.0)], start=(2.0, 0.0))
    add_trajectory(buffer, [(-1.0, 0.0), (1.0, 0.0)], start=(-3.0, 0.0))
    add_trajectory(buffer, [(-1.0, 1.0), (1.0, 1.0)], goal=GOAL + np.array([0.0, 1.0], np.float32), start=(-3.0, 1.0))
    pairs = pairs_of(buffer, [0, 0, 1], [1, 2, 0])
    pairs.shared_goal = np.array([True, False, True])  # as a sampler that relabelled pairs 0 and 2 says
    # Every pair is a tie; each time trajectory 0 began nearer and ended nearer, the other gained more.
    results = tie_answers(pairs, np.full(3, 0.5, np.float32))
    # Start gaps by hand: 0 and 1 start 5 apart with one goal; 0 and 2 also 1 apart across and their goals 1 apart.
    assert results["all"] == {
        "share": 1.0,
        "tie_share": 1.0,
        "start_gap": pytest.approx((10 + 27**0.5) / 3),
        "end_prefers_nearer_start": 1.0,
        "gain_prefers_nearer_start": 0.0,
    }
    assert results["own_goals"]["share"] == 1 / 3 and results["shared_goal"]["share"] == 2 / 3
    assert results["own_goals"]["start_gap"] == pytest.approx(27**0.5) and results["shared_goal"]["start_gap"] == 5.0
    # A label the script decides is no tie; a group without a counted tie answers NaN.
    results = tie_answers(pairs, np.array([1.0, 0.5, 0.0], np.float32))
    assert results["own_goals"]["tie_share"] == 1.0 and results["shared_goal"]["tie_share"] == 0.0
    assert np.isnan(results["shared_goal"]["end_prefers_nearer_start"])


def test_the_script_collects_without_training_and_writes_each_models_answers(tmp_path, monkeypatch, capsys):
    run = tmp_path / "dipper" / "PointMazeFourRooms-v0_1"
    env = make_vec_env("sb3_dipper:PointMazeFourRooms-v0", n_envs=1, seed=0)  # the zoo entry's 200-step episodes
    model = tiny_model(DIPPER, env, switch_kwargs=dict(goal_episode_prob=0.5), preference_source="progress")
    model.learn(300)
    model.save(run / "PointMazeFourRooms-v0.zip")
    arguments = [str(SCRIPT), str(run), "--steps", "400", "--pairs", "100", "--csv", str(tmp_path / "t.csv")]
    monkeypatch.setattr(sys, "argv", arguments)
    tie_answers_script.main()
    report = json.loads((run / "tie_answers.json").read_text())
    assert list(report) == ["all", "own_goals", "shared_goal"]
    assert report["own_goals"]["share"] + report["shared_goal"]["share"] == 1.0
    assert 0.0 <= report["all"]["tie_share"] <= 1.0
    rows = pd.read_csv(tmp_path / "t.csv")
    assert rows["group"].tolist() == list(report) and (rows["steps"] == 300).all()
    monkeypatch.setattr(sys, "argv", [*arguments[:2], "--steps", "0"])
    with pytest.raises(SystemExit) as exit_info:
        tie_answers_script.main()
    assert exit_info.value.code == 2 and "--steps and --pairs must be at least 1" in capsys.readouterr().err
    # The pairs drawn with another matched_control_prob than the model's: each a policy trajectory and a control.
    monkeypatch.setattr(sys, "argv", [*arguments[:6], "--matched-control-prob", "1"])
    tie_answers_script.main()
    assert np.isfinite(json.loads((run / "tie_answers.json").read_text())["all"]["start_gap"])
    monkeypatch.setattr(sys, "argv", [*arguments[:2], "--matched-control-prob", "1.5"])
    with pytest.raises(SystemExit):
        tie_answers_script.main()
    assert "--matched-control-prob must be in [0, 1], got 1.5" in capsys.readouterr().err
