"""zoo_scripts/research/preference_pull.py: which way a trained DIPPER's higher-level loss moves its subgoals."""

import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from stable_baselines3.common.env_util import make_vec_env

from sb3_dipper import DIPPER
from tests.conftest import tiny_model
from zoo_scripts.research import preference_pull as preference_pull_script
from zoo_scripts.research.preference_pull import mean_subgoal_forces, pair_groups, preference_pull

SCRIPT = Path(__file__).resolve().parents[2] / "zoo_scripts" / "research" / "preference_pull.py"
ENV_ID = "PointMazeFourRooms-v0"


def tiny_dipper(env_kwargs: dict | None = None) -> DIPPER:
    """A tiny DIPPER with goal episodes and progress labels, trained 300 steps."""
    env = make_vec_env(f"sb3_dipper:{ENV_ID}", n_envs=1, seed=0, env_kwargs=env_kwargs)
    model = tiny_model(DIPPER, env, switch_kwargs=dict(goal_episode_prob=0.5), preference_source="progress")
    return model.learn(300)


@pytest.fixture(scope="module")
def trained():
    """A tiny DIPPER trained on short episodes, so that it stored several trajectories, and pairs drawn from them."""
    model = tiny_dipper(dict(max_episode_steps=40))
    pairs = model.preference_pipeline.sampler.sample(model.trajectory_buffer, 64, np.random.default_rng(0))
    return model, pairs


def test_the_loss_draws_each_mean_toward_the_preferred_subgoal_and_away_from_the_rejected(trained):
    model, pairs = trained
    pairs.labels = np.ones(len(pairs), np.float32)  # every first trajectory preferred
    means, forces = mean_subgoal_forces(model, pairs)
    assert np.all(forces[~pairs.mask] == 0.0) and np.any(forces[pairs.mask] != 0.0)
    # With the paper's loss (uniform reference, no NLL term) the force on a step's mean is the log-density's gradient,
    # (action - mean) / sigma^2 before the squashing, times the pair's positive weight: toward the stored subgoal on
    # the preferred side, away from it on the rejected side, entry by entry.
    offsets = model.subgoal_space.to_world(pairs.actions) - means
    clear = pairs.mask[..., None] & (np.abs(offsets) > 1e-4)
    assert clear[0].any() and clear[1].any()
    assert np.all(np.sign(forces[0][clear[0]]) == np.sign(offsets[0][clear[0]]))
    assert np.all(np.sign(forces[1][clear[1]]) == -np.sign(offsets[1][clear[1]]))


def test_the_groups_split_the_pairs_and_their_pulls_add_up_to_the_batchs(trained):
    model, pairs = trained
    pairs.labels = model.preference_pipeline.labeler.label(pairs)
    groups = pair_groups(pairs)
    parts = np.stack([groups[name] for name in ("contrast", "own_goals", "shared_goal")]).astype(int)
    assert np.all(parts.sum(axis=0) == 1) and groups["all"].all()
    assert groups["contrast"].any(), "goal episodes give contrast pairs"
    results = preference_pull(model, pairs)
    for column in ("share", "pull_along", "pull_share"):
        total = sum(results[name][column] for name in ("contrast", "own_goals", "shared_goal"))
        assert total == pytest.approx(results["all"][column])
    assert results["all"]["pull_share"] == pytest.approx(1.0)
    assert abs(results["all"]["pull_along"]) <= 1.0


def test_the_script_collects_without_training_and_writes_each_models_pull(tmp_path, monkeypatch, capsys):
    run = tmp_path / "dipper" / f"{ENV_ID}_1"
    tiny_dipper().save(run / f"{ENV_ID}.zip")  # the zoo entry's 200-step episodes
    arguments = [str(SCRIPT), str(run), "--steps", "400", "--pairs", "100", "--csv", str(tmp_path / "p.csv")]
    monkeypatch.setattr(sys, "argv", arguments)
    preference_pull_script.main()
    report = json.loads((run / "preference_pull.json").read_text())
    assert list(report) == ["all", "contrast", "own_goals", "shared_goal"]
    assert report["all"]["share"] == 1.0 and 0.0 <= report["all"]["tie_share"] <= 1.0
    rows = pd.read_csv(tmp_path / "p.csv")
    assert rows["pairs"].tolist() == list(report) and (rows["steps"] == 300).all()
    monkeypatch.setattr(sys, "argv", [*arguments[:2], "--pairs", "0"])
    with pytest.raises(SystemExit) as exit_info:
        preference_pull_script.main()
    assert exit_info.value.code == 2 and "--steps and --pairs must be at least 1" in capsys.readouterr().err
