"""zoo_scripts/research/higher_level_diagnostics.py: the higher level's diagnostics at each evaluation, from hand-written
run folders, as a table, a summary and a figure."""

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from zoo_scripts.research import higher_level_diagnostics as diagnostics

BENCHMARKS = Path(__file__).resolve().parents[2] / "docs" / "benchmarks"

ENV_ID = "MazeA-v0"
STEPS_KEY = "time/total_timesteps"


def write_progress(path, steps, columns):
    """An SB3 progress.csv: ``columns`` maps a key to one value per step, None an empty cell (not logged then)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    header = [STEPS_KEY, *columns]
    lines = [",".join(header)]
    for index, step in enumerate(steps):
        cells = [str(step)] + ["" if values[index] is None else str(values[index]) for values in columns.values()]
        lines.append(",".join(cells))
    path.write_text("\n".join(lines) + "\n")


def write_evaluations(run, steps, success):
    """The zoo's evaluations.npz: two episodes per evaluation, both with the given success."""
    run.mkdir(parents=True, exist_ok=True)
    successes = np.repeat(np.array(success, dtype=float)[:, None], 2, axis=1)
    np.savez(run / "evaluations.npz", timesteps=np.array(steps), results=successes - 1, successes=successes)


def write_run(run, tie_shares=(0.1, 0.2, 0.3, 0.4), evaluations=(150, 300, 450)):
    """A run logging every 100 steps (100..400), evaluated at ``evaluations`` (success 0, then 0.5, then 1)."""
    write_progress(
        run / "progress.csv",
        [100, 200, 300, 400],
        {
            "train/high_tie_share": list(tie_shares),
            # Logged only from step 250 on, as the held-out accuracy is once the first new pairs are labelled.
            "train/high_new_pair_accuracy": [None, None, 0.7, 0.8],
            "rollout/subgoal_distance": [1.0, 0.9, 0.8, 0.7],
        },
    )
    write_evaluations(run, list(evaluations), [0.0, 0.5, 1.0][: len(evaluations)])
    return run


def table_of(argv, tmp_path):
    """Run the tool with ``argv`` and ``--csv``; the CSV it wrote."""
    csv = tmp_path / "out.csv"
    diagnostics.main([*argv, "--csv", str(csv)])
    return pd.read_csv(csv, dtype={"config": str}, keep_default_na=False, na_values=[""])


def refusal(argv, capsys):
    """The error message the tool exits with."""
    with pytest.raises(SystemExit) as exit_info:
        diagnostics.main(argv)
    assert exit_info.value.code != 0
    return capsys.readouterr().err


def test_each_evaluation_takes_the_last_value_logged_at_or_before_its_step(tmp_path):
    run = write_run(tmp_path / "logs" / "dipper" / f"{ENV_ID}_1")
    table = table_of(["--runs", f"a=b={run}"], tmp_path)
    assert list(table.columns) == list(diagnostics.COLUMNS)
    assert table["config"].tolist() == ["a=b"] * 3  # split at the last '='
    assert table["env"].tolist() == [ENV_ID] * 3 and table["seed"].tolist() == [0] * 3
    assert table["timesteps"].tolist() == [150, 300, 450]
    assert table["success"].tolist() == [0.0, 0.5, 1.0]
    assert table["tie_share"].tolist() == [0.1, 0.3, 0.4]
    assert math.isnan(table["heldout_accuracy"][0]) and table["heldout_accuracy"].tolist()[1:] == [0.7, 0.8]
    assert table["subgoal_distance"].tolist() == [1.0, 0.8, 0.7]
    assert table["planned_share"].isna().all()  # never logged: empty cells


def test_dpo_flat_keys_stand_for_the_higher_levels(tmp_path):
    run = tmp_path / f"{ENV_ID}_1"
    write_progress(run / "progress.csv", [100, 200], {"train/tie_share": [0.25, 0.5], "train/dpo_loss": [0.6, 0.5]})
    write_evaluations(run, [200], [1.0])
    table = table_of(["--runs", f"flat={run}"], tmp_path)
    assert table["tie_share"].tolist() == [0.5] and table["dpo_loss"].tolist() == [0.5]


def test_the_seeds_of_a_variant_folder_are_seeds_of_one_config_and_the_summary_means_them(tmp_path, capsys):
    variant = tmp_path / "out" / "default"
    write_run(variant / "seed_0" / "dipper" / f"{ENV_ID}_1", tie_shares=(0.1, 0.2, 0.3, 0.4))
    write_run(variant / "seed_3" / "dipper" / f"{ENV_ID}_1", tie_shares=(0.9, 0.9, 0.9, 0.9))
    # seed_3 was run twice: the later run is read, with a note; it is still running, evaluated twice so far.
    write_run(variant / "seed_3" / "dipper" / f"{ENV_ID}_2", tie_shares=(0.5, 0.6, 0.7, 0.8), evaluations=(150, 300))
    table = table_of(["--runs", f"default={variant}"], tmp_path)
    assert table["seed"].tolist() == [0, 0, 0, 3, 3] and set(table["config"]) == {"default"}
    assert table["tie_share"].tolist() == [0.1, 0.3, 0.4, 0.5, 0.7]
    out, err = capsys.readouterr()
    assert f"seed 3 has several runs on {ENV_ID}; reading the last, {ENV_ID}_2" in err
    summary = diagnostics.final_means(diagnostics.read_table(tmp_path / "out.csv"))
    # At the last evaluation both seeds reached, 300 steps: (0.3 + 0.7) / 2.
    assert summary["default"]["seeds"] == "0, 3" and summary["default"]["steps"] == "300"
    assert summary["default"]["tie_share"] == "0.500" and summary["default"]["success"] == "0.500"
    assert summary["default"]["planned_share"] == "-"
    assert "0, 3" in out and "0.500" in out


def test_a_resumed_runs_logs_are_read_in_step_order(tmp_path):
    run = tmp_path / "logs" / "dipper" / f"{ENV_ID}_1"
    # The part before the pause in part_1/, the resumed part beside it, each with its own keys' order.
    write_progress(run / "part_1" / "progress.csv", [100, 200], {"train/high_tie_share": [0.1, 0.2]})
    write_progress(run / "progress.csv", [300, 400], {"rollout/low_value": [-5, -4], "train/high_tie_share": [0.3, 0.4]})
    write_evaluations(run, [150, 250, 450], [0.0, 0.0, 1.0])
    table = table_of(["--runs", f"resumed={run}"], tmp_path)
    assert table["tie_share"].tolist() == [0.1, 0.2, 0.4]
    assert math.isnan(table["low_value"][1]) and table["low_value"][2] == -4


def test_a_repeated_label_is_refused_naming_it(tmp_path, capsys):
    run = write_run(tmp_path / f"{ENV_ID}_1")
    assert "the label 'twice' twice" in refusal(["--runs", f"twice={run}", f"twice={run}"], capsys)


def test_a_folder_without_runs_is_refused_naming_it(tmp_path, capsys):
    empty = tmp_path / "empty"
    (empty / "seed_0" / "dipper").mkdir(parents=True)
    assert f"{empty}: no zoo run in it" in refusal(["--runs", f"a={empty}"], capsys)


def test_a_run_without_progress_csv_is_refused_naming_it(tmp_path, capsys):
    run = tmp_path / "variant" / "seed_0" / "dipper" / f"{ENV_ID}_1"
    write_evaluations(run, [150], [1.0])
    assert f"{run}: no progress.csv" in refusal(["--runs", f"a={tmp_path / 'variant'}"], capsys)


def test_a_run_without_diagnostics_is_a_warning_and_empty_columns(tmp_path, capsys):
    run = tmp_path / "sac" / f"{ENV_ID}_1"
    write_progress(run / "progress.csv", [100, 200], {"rollout/success_rate": [0.0, 1.0]})
    write_evaluations(run, [200], [1.0])
    table = table_of(["--runs", f"sac={run}"], tmp_path)
    assert table["success"].tolist() == [1.0]
    assert table[[diagnostic.column for diagnostic in diagnostics.DIAGNOSTICS]].isna().all(axis=None)
    assert f"warning: {run}: its progress.csv logs none of the diagnostics" in capsys.readouterr().err


def test_a_csv_lacking_columns_is_refused_naming_it(tmp_path, capsys):
    csv = tmp_path / "old.csv"
    csv.write_text("env,config,seed,timesteps,success\nMazeA-v0,a,0,100,1.0\n")
    err = refusal(["--csv-in", str(csv)], capsys)
    assert f"--csv-in {csv} lacks the columns ['tie_share'," in err


def test_a_csv_written_before_a_diagnostic_was_added_reads_it_as_never_logged(tmp_path):
    run = write_run(tmp_path / f"{ENV_ID}_1")
    table_of(["--runs", f"a={run}"], tmp_path)
    old = tmp_path / "old.csv"
    pd.read_csv(tmp_path / "out.csv").drop(columns=list(diagnostics.ADDED_LATER)).to_csv(old, index=False)
    table = diagnostics.read_table(old)
    assert table[list(diagnostics.ADDED_LATER)].isna().all(axis=None) and len(table) > 0


@pytest.mark.parametrize("path", sorted(BENCHMARKS.glob("higher-level-diagnostics-*.csv")), ids=lambda path: path.name)
def test_every_committed_table_reads_back(path):
    table = diagnostics.read_table(path)
    assert len(table) > 0 and table["success"].notna().all()


def test_the_same_seed_from_two_sources_is_refused(tmp_path, capsys):
    run = write_run(tmp_path / f"{ENV_ID}_1")
    table_of(["--runs", f"a={run}"], tmp_path)
    err = refusal(["--runs", f"a={run}", "--csv-in", str(tmp_path / "out.csv")], capsys)
    assert f"seed 0 of 'a' on {ENV_ID} comes from both {tmp_path / 'out.csv'} and a={run}" in err


def test_the_figure_is_written_and_the_csv_round_trips(tmp_path):
    variant = tmp_path / "variant"
    for seed in (0, 1):
        write_run(variant / f"seed_{seed}" / "dipper" / f"{ENV_ID}_1", tie_shares=(0.1, 0.2, 0.3, 0.4 + seed / 10))
    write_run(tmp_path / "other" / f"{ENV_ID}_1")
    written = tmp_path / "first.csv"
    figure = tmp_path / "figures" / "diagnostics.png"
    args = ["--runs", f"variant={variant}", f"other={tmp_path / 'other' / f'{ENV_ID}_1'}"]
    diagnostics.main([*args, "--csv", str(written), "--plot", str(figure)])
    assert figure.read_bytes().startswith(b"\x89PNG")

    again = tmp_path / "again.csv"
    replotted = tmp_path / "replotted.png"
    diagnostics.main(["--csv-in", str(written), "--csv", str(again), "--plot", str(replotted)])
    assert again.read_text() == written.read_text()
    assert replotted.read_bytes().startswith(b"\x89PNG")

    # A panel per diagnostic with data, a line per configuration (the two seeds of the variant are one).
    fig = diagnostics.draw(diagnostics.read_table(again), ENV_ID)
    titles = [ax.get_title() for ax in fig.axes if ax.get_visible() and ax.get_title()]
    assert titles == ["ties among trained pairs", "held-out pair accuracy", "distance to the subgoal"]
    assert [line.get_label() for line in fig.axes[0].get_lines()] == ["variant", "other"]
    np.testing.assert_allclose(fig.axes[0].get_lines()[0].get_ydata(), [0.1, 0.3, 0.45])


def test_several_envs_need_env_to_be_plotted(tmp_path, capsys):
    maze_a = write_run(tmp_path / "seed_0" / "dipper" / f"{ENV_ID}_1")
    maze_b = write_run(tmp_path / "seed_0" / "dipper" / "MazeB-v0_1")
    runs = ["--runs", f"a={maze_a}", f"b={maze_b}"]
    err = refusal([*runs, "--plot", str(tmp_path / "fig.png")], capsys)
    assert f"the inputs hold several envs ({ENV_ID}, MazeB-v0): pick the one to plot with --env" in err
    assert f"--env Nowhere-v0: no evaluation of it in the inputs (they hold ['{ENV_ID}', 'MazeB-v0'])" in refusal(
        [*runs, "--env", "Nowhere-v0"], capsys
    )
    table = table_of([*runs, "--env", "MazeB-v0", "--plot", str(tmp_path / "fig.png")], tmp_path)
    assert set(table["env"]) == {"MazeB-v0"} and set(table["config"]) == {"b"}
    assert (tmp_path / "fig.png").is_file()
