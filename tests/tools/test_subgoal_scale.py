"""zoo_scripts/research/subgoal_scale.py: a trained model's subgoals moved part of the way back to the goal."""

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sb3_dipper import DIPPER
from sb3_dipper.common.subgoals import ElementSubgoalSpace
from tests.conftest import tiny_pick_and_place_model
from zoo_scripts.configs import evaluate
from zoo_scripts.research.subgoal_scale import main, move_proposals, offset_summary

SCRIPT = Path(__file__).resolve().parents[2] / "zoo_scripts" / "research" / "subgoal_scale.py"

# The fixed pick-and-place's goal is the same in every episode, so a constant proposal lies at one distance from it.
ENV_ID = "FetchPickAndPlaceFixed-v0"


def evaluate_proposing(model: DIPPER, proposal: np.ndarray, scale: float, rng=None) -> dict[str, float]:
    """One episode with the higher level proposing ``proposal`` at every decision, moved by ``move_proposals``; with
    the offsets' summary."""
    model._high_level_actions = lambda _observation, _deterministic: proposal.copy()
    seen = move_proposals(model, scale, rng)
    result = evaluate(model, model.get_env(), 1)  # it restores the model's own higher level when it ends
    return {**result, **offset_summary(np.array(seen["offset"]), np.array(seen["way"]))}


@pytest.mark.parametrize("scale", [0.0, 0.25, 0.5])
def test_a_scale_moves_every_subgoal_that_fraction_of_the_way_from_the_goal(scale):
    model = tiny_pick_and_place_model()
    proposal = np.array([[0.9, -0.8, 0.7]], dtype=np.float32)  # near a corner of the subgoal box, far from the goal
    as_proposed = evaluate_proposing(model, proposal, 1.0)
    scaled = evaluate_proposing(model, proposal, scale)
    assert as_proposed["subgoal_to_goal"] > 0.2
    assert scaled["subgoal_to_goal"] == pytest.approx(scale * as_proposed["subgoal_to_goal"], rel=1e-4)
    # The same proposal and the same goal at every decision: every offset alike, their mean as long as each.
    assert scaled["offset_bias"] == pytest.approx(scaled["subgoal_to_goal"], rel=1e-4, abs=1e-6)
    if scale == 0.0:
        assert scaled["success"] == evaluate(model, model.get_env(), 1, goal_as_subgoal=True)["success"]


def test_a_random_direction_keeps_the_distance_from_the_goal_and_changes_the_subgoal():
    model = tiny_pick_and_place_model()
    proposal = model._subgoal_actions(model.get_env().reset()["desired_goal"]) + np.float32(0.05)  # near the goal
    as_proposed = evaluate_proposing(model, proposal, 0.5)
    turned = evaluate_proposing(model, proposal, 0.5, np.random.default_rng(0))
    assert turned["subgoal_to_goal"] == pytest.approx(as_proposed["subgoal_to_goal"], rel=1e-4)
    assert turned["subgoal_to_achieved"] != pytest.approx(as_proposed["subgoal_to_achieved"], rel=1e-3)
    assert turned["offset_bias"] < 0.5 * as_proposed["offset_bias"]  # turned apart at every decision


def test_the_offsets_summary_splits_them_along_and_beside_the_way_by_hand():
    ways = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    offsets = np.array([[-0.02, 0.03, 0.0], [0.0, 0.04, 0.0]])  # 2 cm short and 3 cm beside; 4 cm past
    summary = offset_summary(offsets, ways)
    assert summary["short_of_goal"] == pytest.approx(0.01)  # (2 + 0) / 2 cm
    assert summary["past_goal"] == pytest.approx(0.02)  # (0 + 4) / 2 cm
    assert summary["beside_way"] == pytest.approx(0.015)  # (3 + 0) / 2 cm
    assert summary["offset_bias"] == pytest.approx(np.hypot(0.01, 0.035))  # the mean offset (-1, 3.5, 0) cm


def test_the_way_runs_from_the_achieved_goal_to_the_goal():
    model = tiny_pick_and_place_model()
    space = model.subgoal_space

    def past_the_goal(observation, _deterministic):  # 3 cm beyond the goal, on the line from the object through it
        goal = space.to_world(model._subgoal_actions(observation["desired_goal"]))
        way = goal - space.to_world(model._subgoal_actions(observation["achieved_goal"], "achieved_goal"))
        return space.to_unit(goal + 0.03 * way / np.linalg.norm(way, axis=-1, keepdims=True))

    model._high_level_actions = past_the_goal
    seen = move_proposals(model, 0.5)
    evaluate(model, model.get_env(), 1)
    assert len(seen["offset"]) == 49 // 7
    summary = offset_summary(np.array(seen["offset"]), np.array(seen["way"]))
    assert summary["past_goal"] == pytest.approx(0.015, abs=1e-5)
    assert summary["short_of_goal"] == pytest.approx(0.0, abs=1e-6)
    assert summary["beside_way"] == pytest.approx(0.0, abs=1e-5)


def test_subgoals_that_are_task_elements_are_refused_with_the_reason():
    model = tiny_pick_and_place_model()
    model.subgoal_space = ElementSubgoalSpace(
        low=np.zeros(2), high=np.ones(2), threshold=0.3, elements=((0,), (1,)), done=np.ones(2), start=np.zeros(2)
    )
    with pytest.raises(ValueError, match="task elements"):
        move_proposals(model, 0.5)


def test_the_script_writes_one_row_per_case_and_refuses_a_scale_beyond_the_subgoal(tmp_path, monkeypatch, capsys):
    run = tmp_path / "dipper" / f"{ENV_ID}_1"
    run.mkdir(parents=True)
    tiny_pick_and_place_model().save(run / f"{ENV_ID}.zip")
    command = [sys.executable, str(SCRIPT), str(run), "--episodes", "1", "--csv", str(tmp_path / "s.csv")]
    done = subprocess.run([*command, "--scales", "1", "--random"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    with open(tmp_path / "s.csv") as file:
        rows = {row["subgoals"]: row for row in csv.DictReader(file)}
    assert list(rows) == ["goal", "policy 1", "random 1"]
    assert float(rows["goal"]["subgoal_to_goal"]) == pytest.approx(0.0, abs=1e-4)
    assert float(rows["policy 1"]["subgoal_to_goal"]) > 0.0
    assert set(json.loads((run / "subgoal_scale.json").read_text())) == set(rows)
    monkeypatch.setattr(sys, "argv", [*command[1:], "--scales", "1.5"])
    with pytest.raises(SystemExit) as refused:
        main()
    assert refused.value.code == 2 and "--scales [1.5]" in capsys.readouterr().err
