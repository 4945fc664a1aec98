"""zoo_scripts/research/clone_demonstration.py: what a task's one demonstration teaches by pure behaviour cloning."""

import csv

import gymnasium as gym
import numpy as np
import pytest

from sb3_dipper.common.imitation import DemonstrationBuffer
from sb3_dipper.envs.demos import default_demonstrations, expert_demonstrations
from zoo_scripts.research.clone_demonstration import (
    first_departure,
    fit_clone,
    goal_conditioned_batches,
    goal_conditioned_inputs,
    main,
    run_clone,
    subgoal_conditioned_batches,
)
from zoo_scripts.research.oracle_subgoals import oracle_subgoals


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
    reference = goal_conditioned_inputs(demonstration)
    sample_batch = goal_conditioned_batches(reference, demonstration.actions, seed=0)
    untrained = run_clone(fit_clone(sample_batch, reference, 4, [64, 64], steps=0), env, demonstration, 0, 0.05)
    assert untrained["success"] == 0.0 and untrained["departure_step"] != ""
    clone = fit_clone(sample_batch, reference, 4, [64, 64], steps=1500)
    assert clone.fit_loss < 1e-3
    episode = run_clone(clone, env, demonstration, 0, 0.05)
    env.close()
    assert episode == {"success": 1.0, "departure_step": "", "episode_steps": 50, "options_reached": ""}


def test_a_clone_trained_as_a_lower_level_follows_the_demonstrations_subgoals():
    # Fitted on the subgoals the lower level's cloning term samples (later achieved subgoals, or the goal), then driven
    # by the demonstration's subgoals at option ends, as oracle_subgoals.py drives a trained lower level.
    demonstration = default_demonstrations("FetchPickAndPlaceFixed-v0").first_episodes(1)
    env = gym.make("FetchPickAndPlaceFixed-v0")
    space = env.unwrapped.subgoal_space
    sample_batch = subgoal_conditioned_batches(DemonstrationBuffer(demonstration, space, demonstration.actions), 0)
    inputs, actions = sample_batch(4)
    assert inputs.shape == (4, demonstration.observations["observation"].shape[1] + space.dim) and actions.shape == (4, 4)
    reference, _ = sample_batch(1000)
    subgoals = oracle_subgoals("FetchPickAndPlaceFixed-v0", 7, space)
    untrained = fit_clone(sample_batch, reference, 4, [64, 64], steps=0)
    driven = run_clone(untrained, env, demonstration, 0, 0.05, subgoals, option_steps=7, space=space)
    assert driven["success"] == 0.0 and float(driven["options_reached"]) < 0.5
    trained = fit_clone(sample_batch, reference, 4, [64, 64], steps=1500)
    driven = run_clone(trained, env, demonstration, 0, 0.05, subgoals, option_steps=7, space=space)
    env.close()
    assert driven["success"] == 1.0 and float(driven["options_reached"]) == 1.0  # all 8 options, the last at step 50


def test_a_clone_driven_by_the_goal_sees_the_projected_goal_as_every_subgoal():
    env = gym.make("FetchPushFixed-v0")
    space = env.unwrapped.subgoal_space
    seen = []

    class Recorder:
        def act(self, observation):
            seen.append(observation["desired_goal"])
            return np.zeros(4, dtype=np.float32)

    demonstration = default_demonstrations("FetchPushFixed-v0").first_episodes(1)
    goal = space.project(env.reset(seed=3)[0]["desired_goal"])
    episode = run_clone(Recorder(), env, demonstration, 3, 0.05, option_steps=7, goal_as_subgoal=True, space=space)
    env.close()
    assert len(seen) == 50 and all(np.array_equal(subgoal, goal) for subgoal in seen)
    assert episode["options_reached"] == "0.0000"  # the arm at rest never brings the block to the goal
    with pytest.raises(ValueError, match="needs their space"):
        run_clone(Recorder(), env, demonstration, 3, 0.05, option_steps=7, goal_as_subgoal=True)


def test_the_command_writes_one_csv_row_per_episode(tmp_path, capsys):
    out = tmp_path / "clone.csv"
    main(["FetchPushFixed-v0", "--net-arch", "16", "--fit-steps", "5", "--episodes", "2", "--csv", str(out)])
    rows = list(csv.DictReader(out.open()))
    assert [(row["env"], row["episode_seed"], row["episode_steps"]) for row in rows] == [
        ("FetchPushFixed-v0", "0", "50"),
        ("FetchPushFixed-v0", "1", "50"),
    ]
    assert "FetchPushFixed-v0, fit seed 0: success 0.00 over 2 episodes" in capsys.readouterr().out
    assert not list(tmp_path.glob("*.tmp*"))


def test_first_episode_seed_runs_episodes_the_demonstrations_did_not_start_from(tmp_path):
    out = tmp_path / "clone.csv"
    arguments = ["FetchPush-v4", "--net-arch", "16", "--fit-steps", "5", "--episodes", "2", "--csv", str(out)]
    main([*arguments, "--first-episode-seed", "20000"])
    assert [row["episode_seed"] for row in csv.DictReader(out.open())] == ["20000", "20001"]
    with pytest.raises(SystemExit):
        main([*arguments, "--first-episode-seed", "-1"])


def test_each_fit_seed_is_a_clone_of_its_own(tmp_path, capsys):
    out = tmp_path / "clone.csv"
    main(
        [
            "FetchPushFixed-v0",
            "--net-arch",
            "16",
            "--fit-steps",
            "5",
            "--episodes",
            "1",
            "--fit-seeds",
            "0",
            "1",
            "0",
            "--csv",
            str(out),
        ]
    )
    rows = list(csv.DictReader(out.open()))
    assert [row["fit_seed"] for row in rows] == ["0", "1", "0"]
    assert rows[0]["fit_loss"] == rows[2]["fit_loss"] != rows[1]["fit_loss"]  # the same seed, the same clone
    assert "fit seed 1: success" in capsys.readouterr().out


def test_the_command_clones_the_first_episodes_of_a_demonstration_file(tmp_path, capsys):
    demos = tmp_path / "dart.npz"
    expert_demonstrations("FetchPushFixed-v0", n_episodes=3, action_noise=0.1).save(demos)
    out = tmp_path / "clone.csv"
    args = ["--net-arch", "16", "--fit-steps", "5", "--episodes", "1", "--csv", str(out), "--demo-path", str(demos)]
    main(["FetchPushFixed-v0", *args, "--n-demos", "1", "2"])
    rows = list(csv.DictReader(out.open()))
    assert [(row["demonstrations"], row["n_demos"]) for row in rows] == [("dart.npz", "1"), ("dart.npz", "2")]
    assert "FetchPushFixed-v0 (2 of dart.npz), fit seed 0: success" in capsys.readouterr().out
    with pytest.raises(ValueError, match="n_demos between 1 and 3"):
        main(["FetchPushFixed-v0", *args, "--n-demos", "4"])
    with pytest.raises(ValueError, match="the env's has"):
        main(["FetchReach-v4", *args])
    with pytest.raises(SystemExit):
        main(["FetchPushFixed-v0", "FetchPickAndPlaceFixed-v0", *args])


def test_a_task_without_a_demonstration_is_named_in_the_error(tmp_path):
    with pytest.raises(ValueError, match="No scripted expert for 'CartPole-v1'"):
        main(["CartPole-v1", "--episodes", "1"])


def test_the_command_clones_as_a_lower_level_with_option_steps(tmp_path, capsys):
    out = tmp_path / "clone.csv"
    args = ["--net-arch", "16", "--fit-steps", "5", "--episodes", "1", "--option-steps", "7", "--csv", str(out)]
    main(["FetchPushFixed-v0", *args])
    (row,) = list(csv.DictReader(out.open()))
    assert row["option_steps"] == "7" and 0.0 <= float(row["options_reached"]) <= 1.0
    assert "FetchPushFixed-v0, fit seed 0: success 0.00, options reached" in capsys.readouterr().out

    # gymnasium-robotics' own ids declare no subgoal space: the clone takes the one the algorithms would train with.
    main(["FetchPush-v4", *args])
    (row,) = list(csv.DictReader(out.open()))
    assert row["env"] == "FetchPush-v4" and 0.0 <= float(row["options_reached"]) <= 1.0
    with pytest.raises(SystemExit):
        main(["FetchPushFixed-v0", *args[:-3], "0"])


def test_the_command_drives_the_clone_by_the_goal_with_drive_goal(tmp_path, capsys):
    out = tmp_path / "clone.csv"
    args = ["--net-arch", "16", "--fit-steps", "5", "--episodes", "1", "--csv", str(out)]
    main(["FetchPushFixed-v0", *args, "--option-steps", "7", "--drive", "goal", "--batch-size", "8"])
    (row,) = list(csv.DictReader(out.open()))
    assert row["driver"] == "goal" and row["option_steps"] == "7" and row["batch_size"] == "8"
    assert "(driven by the goal's subgoals)" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["FetchPushFixed-v0", *args, "--drive", "goal"])  # without --option-steps
    with pytest.raises(SystemExit):
        main(["FetchPushFixed-v0", *args, "--batch-size", "0"])
