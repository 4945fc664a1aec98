"""zoo_scripts/research/label_agreement.py: how often a trained DIPPER's labels agree with oracles of the progress."""

import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from stable_baselines3.common.env_util import make_vec_env

from sb3_dipper import DIPPER
from sb3_dipper.common.preferences import final_path_distances
from sb3_dipper.common.trajectories import TrajectoryBuffer
from sb3_dipper.envs.fetch import MazeGeometry
from tests.conftest import tiny_model
from tests.test_preferences import GOAL, OBS_SPACE, add_trajectory, pairs_of
from zoo_scripts.research import label_agreement as label_agreement_script
from zoo_scripts.research.label_agreement import label_agreement

SCRIPT = Path(__file__).resolve().parents[2] / "zoo_scripts" / "research" / "label_agreement.py"


def test_each_oracle_is_compared_with_the_labels_over_the_pairs_both_decide():
    buffer = TrajectoryBuffer(capacity=4, max_length=2, observation_space=OBS_SPACE, action_dim=2)
    # GOAL is (3, 0). 0: starts 1 away, ends 1.5 away; 1: starts 6 away, ends 2 away; 2: like 1, its own goal (3, 1).
    add_trajectory(buffer, [(2.0, 1.0), (1.5, 0.0)], start=(2.0, 0.0))
    add_trajectory(buffer, [(-1.0, 0.0), (1.0, 0.0)], start=(-3.0, 0.0))
    add_trajectory(buffer, [(-1.0, 1.0), (1.0, 1.0)], goal=GOAL + np.array([0.0, 1.0], np.float32), start=(-3.0, 1.0))
    pairs = pairs_of(buffer, [0, 0, 1], [1, 2, 0])
    pairs.shared_goal = np.array([True, False, True])
    # By hand: the end prefers trajectory 0 in every pair (first, first, second), the gain the other one.
    labels = np.array([1.0, 0.0, 0.5], np.float32)
    paths = np.array([[1.0, 2.0, 3.0], [2.0, 2.0, 1.0]])  # the path prefers the first, ties, prefers the second
    results = label_agreement(pairs, labels, paths)
    assert results["all"] == {
        "share": 1.0,
        "tie_share": pytest.approx(1 / 3),
        "end_agreement": 0.5,
        "end_decided": 1.0,
        "gain_agreement": 0.5,
        "gain_decided": 1.0,
        "path_agreement": 1.0,
        "path_decided": pytest.approx(2 / 3),
    }
    assert results["own_goals"]["end_agreement"] == 0.0 and results["own_goals"]["gain_agreement"] == 1.0
    assert np.isnan(results["own_goals"]["path_agreement"]) and results["own_goals"]["path_decided"] == 0.0
    assert results["shared_goal"]["share"] == pytest.approx(2 / 3) and results["shared_goal"]["end_agreement"] == 1.0
    # Off the mazes there is no path oracle; a label people have not given yet counts neither as a tie nor as decided.
    labels[0] = np.nan
    results = label_agreement(pairs, labels)
    assert np.isnan(results["all"]["path_agreement"]) and np.isnan(results["all"]["path_decided"])
    assert results["all"]["end_agreement"] == 0.0 and results["all"]["tie_share"] == pytest.approx(1 / 3)


def test_the_path_oracle_reads_each_trajectorys_last_option_and_layout(tmp_path, monkeypatch):
    run = tmp_path / "dipper" / "FetchFourRoomMaze-v0_1"
    env = make_vec_env("FetchFourRoomMaze-v0", n_envs=1, seed=0)  # 225-step episodes
    model = tiny_model(DIPPER, env, preference_source="progress").learn(500)
    pairs = model.preference_pipeline.sampler.sample(model.trajectory_buffer, 16, np.random.default_rng(0))
    maze = MazeGeometry()
    distances = final_path_distances(pairs, maze.path_distances)
    last = pairs.mask.sum(axis=-1) - 1
    side, index = 1, 3
    step = last[side, index]
    expected = maze.path_distances(
        pairs.observations["observation"][side, index, step],
        pairs.next_achieved_goals[side, index, step],
        pairs.observations["desired_goal"][side, index, step],
    )
    assert distances.shape == pairs.mask.shape[:2] and distances[side, index] == expected[0]
    assert np.all(np.isfinite(distances)) and np.all(distances >= 0.0)
    # The script end to end: the maze's path oracle is measured, per group, into the run's JSON and the CSV.
    model.save(run / "FetchFourRoomMaze-v0.zip")
    arguments = [str(SCRIPT), str(run), "--steps", "500", "--pairs", "50", "--csv", str(tmp_path / "a.csv")]
    monkeypatch.setattr(sys, "argv", arguments)
    label_agreement_script.main()
    report = json.loads((run / "label_agreement.json").read_text())
    assert list(report) == ["all", "own_goals", "shared_goal"] and 0.0 <= report["all"]["path_decided"] <= 1.0
    rows = pd.read_csv(tmp_path / "a.csv")
    assert rows["group"].tolist() == list(report) and (rows["steps"] == 500).all()
