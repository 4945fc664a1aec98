"""The results matrix (zoo_scripts/report.py): each cell from the committed CSVs, written between markers."""

from pathlib import Path

import pytest

from zoo_scripts import report

LEARNING = """env,algo,seed,timesteps,success,subgoal_distance,low_value,train_success,preference_pairs,finished
FetchPickAndPlaceFixed-v0,sac,0,135000,1.0000,,,0.1,,1
FetchPickAndPlaceFixed-v0,sac,0,150000,0.0000,,,0.1,,1
FetchPickAndPlaceFixed-v0,sac,0,165000,1.0000,,,0.1,,1
FetchPickAndPlaceFixed-v0,sac,1,150000,1.0000,,,0.1,,1
FetchPickAndPlaceFixed-v0,hier,0,90000,0.5000,,,0.1,,0
"""
SHARE = """run,steps,case,success,planned_share
runs/a/seed_0/dipper/FetchPickAndPlaceFixed-v0_1,60000,lower_level_alone,0.1000,0.0000
runs/a/seed_0/dipper/FetchPickAndPlaceFixed-v0_1,150000,lower_level_alone,0.9000,0.0000
runs/a/seed_1/dipper/FetchPickAndPlaceFixed-v0_1,150000,lower_level_alone,0.7000,0.0000
runs/a/seed_1/dipper/FetchPickAndPlaceFixed-v0_1,150000,policy_alone,0.2000,0.0000
"""


@pytest.fixture
def results(tmp_path, monkeypatch) -> Path:
    (tmp_path / "paper-tasks-cpu.csv").write_text(LEARNING)
    (tmp_path / "share.csv").write_text(SHARE)
    monkeypatch.setattr(report, "RESULTS", tmp_path)
    return tmp_path


def test_a_learning_cell_is_each_seeds_last_evaluation_within_the_budget(results):
    cell, curves = report.learning_cell("FetchPickAndPlaceFixed-v0", report.Learning("sac"))
    # Seed 0's evaluation at 165k lies past the 150k budget: its 0.00 at 150k counts.
    assert cell.success == [0.0, 1.0] and cell.text() == "0.50 +- 0.50 (2)"
    assert [len(steps) for steps, _ in curves] == [2, 1]
    partial, _ = report.learning_cell("FetchPickAndPlaceFixed-v0", report.Learning("hier"))
    assert partial.text() == "0.50 (1*)"
    empty, _ = report.learning_cell("FetchPickAndPlaceFixed-v0", report.Learning("piper"))
    assert empty.text() == ""


def test_a_cell_shows_the_earlier_profiles_runs_marked_until_the_method_is_rerun(results):
    earlier = report.Learning("piper", earlier="sac")
    cell, curves = report.learning_cell("FetchPickAndPlaceFixed-v0", earlier)
    assert cell.earlier and cell.label == "sac" and cell.text() == "0.50 +- 0.50 (2)†" and len(curves) == 2
    rerun = report.Learning("hier", earlier="sac")
    cell, _ = report.learning_cell("FetchPickAndPlaceFixed-v0", rerun)
    assert not cell.earlier and cell.label == "hier" and cell.text() == "0.50 (1*)"


def test_the_earlier_profiles_labels_name_what_changed():
    fixed, push = "FetchPickAndPlaceFixed-v0", "FetchPushFixed-v0"
    assert report.earlier_label("piper", fixed) == "piper-highauto-bc0.0078"
    assert report.earlier_label("piper", push) == "piper-highauto"
    dart = report.earlier_label("hier-dart20-noqf-bc1-demo0.5", "FetchPickAndPlace-v4")
    assert dart == "hier-highauto-dart20-noqf-bc1-demo0.5"
    assert report.earlier_label("raps", fixed) == "raps-hightau0.005"
    assert report.earlier_label("dipper_paper-lambda0", fixed) == "dipper_paper-bc0.0078-lambda0"
    assert report.earlier_label("dipper_paper", push) is None and report.earlier_label("sac_demo", fixed) is None


def test_an_evaluated_cell_takes_each_runs_final_model_of_its_case(results):
    cell = report.evaluated_cell(report.Evaluated("share.csv", "FetchPickAndPlaceFixed", "lower_level_alone"))
    assert sorted(cell.success) == [0.7, 0.9] and cell.text() == "0.80 +- 0.10 (2)"
    assert report.evaluated_cell(report.Evaluated("missing.csv", "x", "policy_alone")).text() == ""


def test_a_cells_speed_is_the_mean_over_the_finished_runs_that_recorded_it(results):
    (results / "timed.csv").write_text(
        "env,algo,seed,timesteps,success,subgoal_distance,low_value,train_success,preference_pairs,finished,"
        "steps_per_second,commit\n"
        "FetchPickAndPlaceFixed-v0,hac,0,150000,1.0000,,,0.1,,1,150.0,abc\n"
        "FetchPickAndPlaceFixed-v0,hac,1,150000,0.0000,,,0.1,,1,100.0,abc\n"
        "FetchPickAndPlaceFixed-v0,hac,2,150000,0.0000,,,0.1,,1,,abc\n"
    )
    timed, _ = report.learning_cell("FetchPickAndPlaceFixed-v0", report.Learning("hac", "timed.csv"))
    assert timed.speeds == [150.0, 100.0]
    untimed, _ = report.learning_cell("FetchPickAndPlaceFixed-v0", report.Learning("sac"))
    assert untimed.speeds == []
    rows = [
        ["task", "column", "source", "seeds", "success", "steps_per_second", "speed_runs"],
        ["FetchPushFixed-v0", "SAC+HER", "sac", "1", "0.00 (1)", "", "0"],
        ["FetchPushFixed-v0", "HAC", "hac", "3", "0.33 +- 0.47 (3)", "125", "2"],
        ["FetchPickAndPlaceFixed-v0", "HAC", "hac", "3", "0.33 +- 0.47 (3)", "140", "3"],
    ]
    table = report.cell_speeds(rows).splitlines()
    assert table[2:] == [
        "| `FetchPickAndPlaceFixed-v0` | HAC | `hac` | 3 of 3 | 140 |",
        "| `FetchPushFixed-v0` | HAC | `hac` | 2 of 3 | 125 |",
    ]


def test_whose_success_has_a_row_per_method_and_task_from_its_final_models(results, monkeypatch):
    monkeypatch.setattr(report, "BASELINE_FINAL_MODELS", [("FetchPickAndPlaceFixed-v0", "HAC", "share.csv", "/dipper/")])
    table = report.whose_success().splitlines()
    assert table[0] == "| task | method | as trained | higher policy untrained | goal as every subgoal |"
    assert table[2] == "| `FetchPickAndPlaceFixed-v0` | HAC |  |  | 0.80 +- 0.10 (2) |"


def test_the_matrix_is_written_between_the_markers_and_refused_without_them(results, tmp_path):
    document = tmp_path / "doc.md"
    document.write_text("before\n<!-- results-matrix -->\nold table\n<!-- /results-matrix -->\nafter\n")
    report.write_between_markers(document, "| new |")
    assert document.read_text() == "before\n<!-- results-matrix -->\n| new |\n<!-- /results-matrix -->\nafter\n"
    (tmp_path / "plain.md").write_text("no markers\n")
    with pytest.raises(SystemExit, match="no <!-- results-matrix -->"):
        report.write_between_markers(tmp_path / "plain.md", "| new |")
    with pytest.raises(SystemExit, match="no <!-- whose-success -->"):
        report.write_between_markers(document, "| new |", "whose-success")


def test_each_tasks_demonstrations_are_read_from_dippers_profile():
    assert report.profile_demonstrations("FetchPickAndPlaceFixed-v0") == "1 demonstration"
    assert report.profile_demonstrations("FetchPush-v4") == "200 DART episodes"
    assert report.profile_demonstrations("FetchFourRoomMazeFixed-v0") == "no demonstrations"


def test_every_column_names_one_configuration_per_task():
    tables, rows, _ = report.matrix()
    assert tables.count("| task (budget, demonstrations) |") == 3
    # Every CSV row names the one source of its cell.
    assert rows[0][:5] == ["task", "column", "source", "seeds", "success"] and all(len(row) == 7 for row in rows)
    for heading, sources in [*report.DIPPER_COLUMNS, *report.HIERARCHICAL_COLUMNS, *report.FLAT_COLUMNS]:
        assert set(sources) <= set(report.TASKS), heading


def test_the_ablations_take_the_papers_value_from_its_own_rows(results, monkeypatch):
    (results / "ablations.csv").write_text(
        LEARNING.splitlines()[0]
        + "\nFetchPickAndPlaceFixed-v0,dipper_paper-beta1,0,75000,1.0000,,,0.1,,1"
        + "\nFetchPickAndPlaceFixed-v0,dipper_paper-beta1,0,150000,0.0000,,,0.1,,1\n"
    )
    monkeypatch.setattr(
        report,
        "ABLATIONS",
        [("beta", [("0.1", report.Learning("sac")), ("1", report.Learning("dipper_paper-beta1", "ablations.csv"))])],
    )
    table, panels = report.ablations()
    rows = table.splitlines()
    assert rows[2] == "| beta | 0.1 | 0.50 +- 0.50 (2) | 1 of 2, 1 of 1 | 0.67 |"
    assert rows[3] == "| beta | 1 | 0.00 (1) | 1 of 2 | 0.50 |"
    assert list(panels) == ["beta, fixed pick-and-place"]
    assert list(panels["beta, fixed pick-and-place"]) == ["beta = 0.1", "beta = 1"]


def test_evaluations_with_success_count_every_evaluation_within_the_budget(results):
    _, curves = report.learning_cell("FetchPickAndPlaceFixed-v0", report.Learning("sac"))
    table = report.evaluations_with_success({"FetchPickAndPlaceFixed-v0": {"SAC+HER": curves}}).splitlines()
    # Seed 0 succeeded at 135k, not at 150k (its 1.00 at 165k lies past the budget); seed 1 at its one evaluation.
    assert table[0] == "| column | evaluations with success, per seed | of all |"
    assert table[2:] == ["| SAC+HER | 1 of 2, 1 of 1 | 2 of 3 |"]
