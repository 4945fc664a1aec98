"""zoo_scripts/clone_demonstration.py: what a task's one demonstration teaches by pure behaviour cloning."""

import csv

import gymnasium as gym
import numpy as np
import pytest

from sb3_dipper.envs.demos import default_demonstrations, expert_demonstrations
from zoo_scripts.clone_demonstration import first_departure, fit_clone, main, run_clone


def test_the_departure_is_the_first_step_off_the_demonstrated_states():
    demonstrated = np.zeros((5, 2))
    states = np.array([[0.0, 0.01], [0.02, 0.0], [0.0, 0.3], [0.0, 0.0], [1.0, 1.0]])
    assert first_departure(states, demonstrated, tolerance=0.05) == 2
    assert first_departure(states[:2], demonstrated, tolerance=0.05) is None
    # Steps beyond the demonstration's end are not compared.
    assert first_departure(np.zeros((8, 2)), demonstrated, tolerance=0.05) is None


def test_a_clone_of_the_fixed_pick_and_place_demonstration_solves_it_closed_loop():
    # The fixed task starts where its demonstration started and the expert's 50 steps are smooth: cloning alone is
    # enough there (BENCHMARKS.md, "what one demonstration teaches"). An unfitted network fails.
    demonstration = default_demonstrations("FetchPickAndPlaceFixed-v0").first_episodes(1)
    env = gym.make("FetchPickAndPlaceFixed-v0")
    untrained = run_clone(fit_clone(demonstration, [64, 64], steps=0), env, demonstration, 0, 0.05)
    assert untrained["success"] == 0.0 and untrained["departure_step"] != ""
    clone = fit_clone(demonstration, [64, 64], steps=1500)
    assert clone.fit_loss < 1e-3
    episode = run_clone(clone, env, demonstration, 0, 0.05)
    env.close()
    assert episode == {"success": 1.0, "departure_step": "", "episode_steps": 50}


def test_the_command_writes_one_csv_row_per_episode(tmp_path, capsys):
    out = tmp_path / "clone.csv"
    main(["FetchPushFixed-v0", "--net-arch", "16", "--fit-steps", "5", "--episodes", "2", "--csv", str(out)])
    rows = list(csv.DictReader(out.open()))
    assert [(row["env"], row["episode_seed"], row["episode_steps"]) for row in rows] == [
        ("FetchPushFixed-v0", "0", "50"),
        ("FetchPushFixed-v0", "1", "50"),
    ]
    assert "FetchPushFixed-v0: success 0.00 over 2 episodes" in capsys.readouterr().out
    assert not list(tmp_path.glob("*.tmp*"))


def test_the_command_clones_the_first_episodes_of_a_demonstration_file(tmp_path, capsys):
    demos = tmp_path / "dart.npz"
    expert_demonstrations("FetchPushFixed-v0", n_episodes=3, action_noise=0.1).save(demos)
    out = tmp_path / "clone.csv"
    args = ["--net-arch", "16", "--fit-steps", "5", "--episodes", "1", "--csv", str(out), "--demo-path", str(demos)]
    main(["FetchPushFixed-v0", *args, "--n-demos", "1", "2"])
    rows = list(csv.DictReader(out.open()))
    assert [(row["demonstrations"], row["n_demos"]) for row in rows] == [("dart.npz", "1"), ("dart.npz", "2")]
    assert "FetchPushFixed-v0 (2 of dart.npz): success" in capsys.readouterr().out
    with pytest.raises(ValueError, match="n_demos between 1 and 3"):
        main(["FetchPushFixed-v0", *args, "--n-demos", "4"])
    with pytest.raises(ValueError, match="the env's has"):
        main(["FetchReach-v4", *args])
    with pytest.raises(SystemExit):
        main(["FetchPushFixed-v0", "FetchPickAndPlaceFixed-v0", *args])


def test_a_task_without_a_demonstration_is_named_in_the_error(tmp_path):
    with pytest.raises(ValueError, match="No scripted expert for 'CartPole-v1'"):
        main(["CartPole-v1", "--episodes", "1"])
