"""zoo_scripts/research/oracle_subgoals.py: a trained model driven by the demonstration's subgoals, beside its own higher
level."""

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from stable_baselines3 import SAC
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize

from sb3_dipper import DIPPER
from sb3_dipper.envs.demos import default_demonstrations
from sb3_dipper.envs.fetch import FIXED_OBJECT_XY, FIXED_PICK_AND_PLACE_GOAL, OBJECT_REST_Z
from tests.conftest import tiny_model, tiny_pick_and_place_model
from zoo_scripts.configs import trained_run
from zoo_scripts.research.oracle_subgoals import oracle_subgoals, run_episodes

SCRIPT = Path(__file__).resolve().parents[2] / "zoo_scripts" / "research" / "oracle_subgoals.py"

ENV_ID = "FetchPickAndPlaceFixed-v0"


def test_the_oracle_subgoals_are_the_demonstrations_positions_at_option_ends():
    subgoals = oracle_subgoals(ENV_ID, 7, tiny_pick_and_place_model().subgoal_space)
    # 50 demo steps: the ends of options 1..7 (steps 7, 14, ..., 49) and the last step.
    assert subgoals.shape == (8, 3)
    np.testing.assert_allclose(subgoals[0], [*FIXED_OBJECT_XY, OBJECT_REST_Z], atol=0.01)  # not lifted yet at step 7
    assert subgoals[1, 2] > OBJECT_REST_Z + 0.05  # lifted by step 14
    np.testing.assert_allclose(subgoals[-1], FIXED_PICK_AND_PLACE_GOAL, atol=0.05)


def test_the_script_reads_a_zoo_run_folder_and_writes_its_report(tmp_path):
    run = tmp_path / "dipper" / f"{ENV_ID}_1"
    run.mkdir(parents=True)
    model = tiny_pick_and_place_model()
    model.learn(100)
    model.save(run / f"{ENV_ID}.zip")
    command = [sys.executable, str(SCRIPT), str(run), "--algo", "dipper", "--episodes", "2"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads((run / "oracle_subgoals.json").read_text())
    for driver in ("oracle", "higher_level"):
        assert 0.0 <= report[driver]["success"] <= 1.0 and 0.0 <= report[driver]["options_reached"] <= 1.0
    # The first oracle subgoal is where the object rests, reached by leaving it there.
    assert report["oracle"]["options_reached"] >= 1 / 8


def test_every_episode_starts_where_the_demonstration_started_on_a_random_task():
    env_id = "FetchPickAndPlace-v4"
    env = make_vec_env(env_id, n_envs=1, seed=123)
    model = DIPPER(
        "MultiInputPolicy", env, option_steps=7, learning_starts=50, batch_size=16, buffer_size=500, seed=0,
        n_preference_pairs=50, pairs_per_batch=4, trajectory_buffer_size=20,
        low_policy_kwargs=dict(net_arch=[16]), policy_kwargs=dict(net_arch=[16]),
    )  # fmt: skip
    starts = []
    reset = env.reset

    def recorded_reset():
        observation = reset()
        starts.append(observation["observation"][0].copy())
        return observation

    env.reset = recorded_reset
    result = run_episodes(model, env, 2, oracle_subgoals(env_id, 7, model.subgoal_space))
    demonstration = default_demonstrations(env_id).first_episodes(1)
    assert len(starts) == 2 and 0.0 <= result["options_reached"] <= 1.0
    for start in starts:
        np.testing.assert_allclose(start, demonstration.observations["observation"][0], atol=1e-6)


def test_checkpoints_give_one_csv_row_per_model_and_driver(tmp_path):
    run = tmp_path / "dipper" / f"{ENV_ID}_1"
    run.mkdir(parents=True)
    model = tiny_pick_and_place_model()
    model.learn(60)
    first = str(model.num_timesteps)
    model.save(run / "rl_model_60_steps.zip")
    model.learn(60, reset_num_timesteps=False)
    final = str(model.num_timesteps)
    model.save(run / f"{ENV_ID}.zip")
    command = [sys.executable, str(SCRIPT), str(run), "--algo", "dipper", "--checkpoints", "--csv", str(tmp_path / "c.csv")]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    with open(tmp_path / "c.csv") as file:
        rows = list(csv.DictReader(file))
    assert [(row["steps"], row["driver"]) for row in rows] == [
        (first, "oracle"), (first, "higher_level"), (final, "oracle"), (final, "higher_level")
    ]  # fmt: skip
    assert (run / "oracle_subgoals.json").exists()


def test_a_flat_model_is_refused_with_the_reason(tmp_path):
    run = tmp_path / "sac" / f"{ENV_ID}_1"
    run.mkdir(parents=True)
    SAC("MultiInputPolicy", make_vec_env(ENV_ID, n_envs=1, seed=0), learning_starts=10, batch_size=8).save(
        run / f"{ENV_ID}.zip"
    )
    done = subprocess.run(
        [sys.executable, str(SCRIPT), str(run), "--algo", "sac"], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 2
    assert "not a hierarchical algorithm" in done.stderr


def test_a_run_still_training_is_measured_at_its_checkpoints_and_without_them_refused(tmp_path):
    run = tmp_path / "dipper" / f"{ENV_ID}_1"
    run.mkdir(parents=True)
    model = tiny_pick_and_place_model()
    model.learn(60)
    model.save(run / "rl_model_60_steps.zip")  # no final model yet: the run is still training
    command = [sys.executable, str(SCRIPT), str(run), "--algo", "dipper", "--csv", str(tmp_path / "c.csv")]
    refused = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert refused.returncode == 2
    assert "has not finished" in refused.stderr and "--checkpoints" in refused.stderr
    measured = subprocess.run([*command, "--checkpoints"], capture_output=True, text=True, timeout=300)
    assert measured.returncode == 0, measured.stderr[-3000:]
    with open(tmp_path / "c.csv") as file:
        assert [row["driver"] for row in csv.DictReader(file)] == ["oracle", "higher_level"]
    assert not (run / "oracle_subgoals.json").exists()  # the report is the final model's


def test_a_checkpoint_is_measured_with_the_normalisation_statistics_of_its_own_step(tmp_path):
    # rl-zoo3 keeps one vecnormalize.pkl per run; a checkpoint measured with it would see other statistics than it
    # trained with. The hierarchical model's own copy (its lower level's normaliser) is what the measurement uses.
    env_id = "PointMazeFourRooms-v0"
    run = tmp_path / "dipper" / f"{env_id}_1"
    (run / env_id).mkdir(parents=True)
    env = VecNormalize(make_vec_env(f"sb3_dipper:{env_id}", n_envs=1, seed=0), norm_reward=False)  # full episodes
    model = tiny_model(DIPPER, env)
    model.learn(100)
    model.save(run / "rl_model_100_steps.zip")
    at_checkpoint = env.obs_rms["observation"].mean.copy()
    model.learn(200, reset_num_timesteps=False)
    model.save(run / f"{env_id}.zip")
    env.save(str(run / env_id / "vecnormalize.pkl"))
    at_the_end = env.obs_rms["observation"].mean.copy()
    assert not np.allclose(at_checkpoint, at_the_end)
    _, checkpoint_env = trained_run(run, "dipper", env_id, seed=0, model_file=run / "rl_model_100_steps.zip")
    np.testing.assert_allclose(checkpoint_env.obs_rms["observation"].mean, at_checkpoint)
    assert not checkpoint_env.training
    _, final_env = trained_run(run, "dipper", env_id, seed=0)
    np.testing.assert_allclose(final_env.obs_rms["observation"].mean, at_the_end)
