"""``zoo_scripts/plot.py``: figures from hand-written zoo log folders, one or several (a benchmark's seed folders).

Real zoo runs, written by ``benchmark.py learning``, are plotted in tests/tools/test_benchmark.py.
"""

import json
import re
import sys

import matplotlib
import numpy as np
import pytest

from tests.test_files import truncate
from zoo_scripts import plot

ENVS = ["MazeA-v0", "MazeB-v0"]
SEEDS = [0, 1]
STEPS = np.arange(1, 6) * 1000


def write_run(folder, algo, env_id, seed, evaluations=True, hierarchical=True, run_id=None):
    """One zoo run folder: evaluations.npz, a monitor file with is_success, and an SB3 progress.csv."""
    run = folder / algo / f"{env_id}_{run_id or seed + 1}"
    run.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    success = np.clip(np.linspace(0, 1, len(STEPS))[:, None] + rng.normal(0, 0.1, (len(STEPS), 4)), 0, 1).round()
    if evaluations:
        np.savez(
            run / "evaluations.npz",
            timesteps=STEPS,
            results=success - 1,
            ep_lengths=np.full_like(success, 50),
            successes=success,
        )
    episodes = "\n".join(f"{-50.0},50,{t:.1f},{float(t > 60)}" for t in range(100))
    (run / "0.monitor.csv").write_text(f"#{json.dumps({'t_start': 0.0, 'env_id': env_id})}\nr,l,t,is_success\n{episodes}\n")
    header, rows = (
        "time/total_timesteps,rollout/success_rate",
        [f"{t},{s}" for t, s in zip(STEPS, success.mean(axis=1), strict=True)],
    )
    if hierarchical:
        # rollout/low_value is logged only after learning_starts: empty cells, as SB3's CSV logger writes them.
        header += ",rollout/subgoal_distance,rollout/low_value"
        rows = [f"{row},{1 / t},{'' if i == 0 else -t / 1000}" for i, (row, t) in enumerate(zip(rows, STEPS, strict=True))]
    (run / "progress.csv").write_text("\n".join([header, *rows]) + "\n")


@pytest.fixture
def logs(tmp_path):
    """DIPPER with evaluations and hierarchical metrics, SAC with monitor files only and no hierarchical metrics."""
    for env_id in ENVS:
        for seed in SEEDS:
            write_run(tmp_path / "logs", "dipper", env_id, seed)
            write_run(tmp_path / "logs", "sac", env_id, seed, evaluations=False, hierarchical=False)
    return tmp_path / "logs"


def test_success_figure_has_a_line_and_a_band_per_algorithm_in_every_panel(logs, tmp_path):
    fig = plot.plot_success([logs], ["dipper", "sac"], ENVS, window=10)
    assert [ax.get_title() for ax in fig.axes] == ENVS
    for ax in fig.axes:
        assert [line.get_label() for line in ax.get_lines()] == ["DIPPER", "SAC+HER"]
        assert len(ax.collections) == 2  # the standard-deviation bands
        np.testing.assert_array_equal(ax.get_lines()[0].get_xdata(), STEPS)  # evaluations, not the monitor
    assert [text.get_text() for text in fig.legends[0].get_texts()] == ["DIPPER", "SAC+HER"]
    written = plot.save(fig, tmp_path / "figures" / "success", ["png", "pdf"])
    assert all(path.stat().st_size > 0 for path in written) and len(written) == 2


def test_a_long_shared_legend_stays_below_every_panel():
    curve = (np.array([15_000.0, 30_000.0]), np.array([0.0, 1.0]))
    panels = {env_id: {f"dipper-variant{index}": [curve] for index in range(40)} for env_id in ("A-v0", "B-v0")}
    fig = plot.draw_success(panels)
    fig.canvas.draw()
    legend_top = fig.legends[0].get_window_extent().y1
    assert all(legend_top <= ax.get_tightbbox().y0 for ax in fig.axes if ax.get_visible())


def test_success_is_the_mean_over_seeds_and_monitor_runs_are_smoothed(logs):
    dipper_runs = plot.find_runs([logs], "dipper", ENVS[0])
    steps, mean, std = plot.aggregate([plot.success_curve(run) for run in dipper_runs])
    expected = np.stack([np.load(run / "evaluations.npz")["successes"].mean(axis=1) for run in dipper_runs])
    np.testing.assert_allclose(mean, expected.mean(axis=0))
    np.testing.assert_allclose(std, expected.std(axis=0))
    steps, success = plot.success_curve(plot.find_runs([logs], "sac", ENVS[0])[0], window=10)
    np.testing.assert_array_equal(steps, np.arange(1, 101) * 50)
    assert success[60] == 0 and success[65] == pytest.approx(0.5) and success[-1] == 1


def test_a_damaged_evaluation_record_is_an_error_naming_it(logs):
    """A record cut short (a run killed while SB3 rewrote it in place) failed with a BadZipFile naming no file."""
    run = logs / "dipper" / f"{ENVS[0]}_1"
    truncate(run / "evaluations.npz")
    with pytest.raises(ValueError, match=r"Malformed evaluation record .*evaluations\.npz: not a complete npz archive"):
        plot.evaluation_curve(run)
    with pytest.raises(ValueError, match=r"restore it from a copy of the run folder, or delete it"):
        plot.plot_success([logs], ["dipper"], ENVS)


@pytest.mark.parametrize(
    "damage, problem",
    [
        (lambda lines: [*lines[:3], lines[3].rsplit(",", 1)[0], *lines[4:]], "line 4 has 3 fields, the header 4"),
        (lambda lines: [*lines[:2], lines[3], lines[2], *lines[4:]], "line 4 logs time/total_timesteps 2000 after 3000"),
    ],
)
def test_a_damaged_progress_csv_is_an_error_naming_it(logs, damage, problem):
    """A progress.csv cut and spliced by a run killed while SB3 rewrote it in place was plotted as it was."""
    progress = logs / "dipper" / f"{ENVS[0]}_1" / "progress.csv"
    progress.write_text("\n".join(damage(progress.read_text().splitlines())) + "\n")
    message = rf"{re.escape(str(progress))}: {problem}.* delete line 4 and the lines after it"
    with pytest.raises(ValueError, match=message):
        plot.load_progress(progress.parent)
    with pytest.raises(ValueError, match=message):
        plot.plot_hierarchical_metrics([logs], ["dipper"], ENVS)


def test_hierarchical_metrics_skip_algorithms_without_them(logs):
    fig = plot.plot_hierarchical_metrics([logs], ["dipper", "sac"], ENVS)
    assert fig is not None and len(fig.axes) == 4
    for ax in fig.axes:
        assert [line.get_label() for line in ax.get_lines()] == ["DIPPER"]
    low_value = fig.axes[2].get_lines()[0]
    np.testing.assert_array_equal(low_value.get_xdata(), STEPS[1:])  # the empty cells are dropped
    assert plot.plot_hierarchical_metrics([logs], ["sac"], ENVS) is None


def test_cli_writes_every_figure_and_the_iqm_table(logs, tmp_path, monkeypatch, capsys):
    out = tmp_path / "figures"
    argv = ["plot.py", "-f", str(logs), "--algos", "dipper", "sac", "--envs", *ENVS, "--out", str(out), "--iqm"]
    monkeypatch.setattr(sys, "argv", [*argv, "--reps", "50", "--format", "png"])
    plot.main()
    names = {"success", "hierarchical_metrics", "final_success_iqm"}
    expected = {f"{name}.png" for name in names} | {"final_success_iqm.csv"}
    assert {path.name for path in out.iterdir()} == expected
    assert set(capsys.readouterr().out.split()) == {str(out / name) for name in expected}


def test_iqm_has_one_bar_per_algorithm_and_env(logs):
    table = plot.final_success_iqm([logs], ["dipper", "sac"], ENVS, window=10, reps=50)
    assert len(table) == 4 and (table["n_runs"] == 2).all()
    assert ((table["low"] <= table["iqm"]) & (table["iqm"] <= table["high"])).all()
    assert table.set_index(["algo", "env"]).loc[("sac", ENVS[0]), "iqm"] == 1  # the last 10 episodes all succeeded
    fig = plot.plot_iqm(table)
    assert [len(ax.patches) for ax in fig.axes] == [2, 2]


def test_a_missing_run_folder_is_a_clear_error(logs, tmp_path, monkeypatch, capsys):
    with pytest.raises(FileNotFoundError, match="no runs of hier on MazeA-v0"):
        plot.find_runs([logs], "hier", "MazeA-v0")
    argv = ["plot.py", "-f", str(logs), "--algos", "dipper", "--envs", "MazeC-v0", "--out", str(tmp_path / "figures")]
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit) as exit_info:
        plot.main()
    assert exit_info.value.code == 1
    assert "no runs of dipper on MazeC-v0" in capsys.readouterr().err
    (logs / "dipper" / "MazeC-v0_1").mkdir()
    with pytest.raises(FileNotFoundError, match="has no success data"):
        plot.plot_success([logs], ["dipper"], ["MazeC-v0"])


def test_seeds_in_several_log_folders_as_benchmark_py_writes_them(tmp_path, monkeypatch, capsys):
    """``-f`` takes several log folders (a benchmark's ``<out>/<variant>/seed_<n>``): their runs are the seeds."""
    seed_folders = [tmp_path / "benchmark" / "default" / f"seed_{seed}" for seed in SEEDS]
    for seed, folder in zip(SEEDS, seed_folders, strict=True):
        write_run(folder, "dipper", ENVS[0], seed, run_id=1)
    runs = plot.find_runs(seed_folders, "dipper", ENVS[0])
    assert runs == [folder / "dipper" / f"{ENVS[0]}_1" for folder in seed_folders]
    out = tmp_path / "figures"
    argv = ["plot.py", "-f", *map(str, seed_folders), "--algos", "dipper", "--envs", ENVS[0], "--out", str(out)]
    monkeypatch.setattr(sys, "argv", [*argv, "--format", "png"])
    plot.main()
    assert {path.name for path in out.iterdir()} == {"success.png", "hierarchical_metrics.png"}
    fig = plot.plot_success(seed_folders, ["dipper"], [ENVS[0]])
    expected = np.mean([np.load(run / "evaluations.npz")["successes"].mean(axis=1) for run in runs], axis=0)
    np.testing.assert_allclose(fig.axes[0].get_lines()[0].get_ydata(), expected)


def test_a_run_still_going_cuts_the_curves_at_the_evaluations_every_seed_has():
    finished, going = (STEPS.astype(float), np.linspace(0, 1, 5)), (STEPS[:3].astype(float), np.full(3, 0.5))
    steps, values = plot.align([finished, going])
    np.testing.assert_array_equal(steps, STEPS[:3])
    np.testing.assert_allclose(values, [[0, 0.25, 0.5], [0.5, 0.5, 0.5]])
    # Curves measured at other steps are interpolated over the range both cover.
    steps, values = plot.align([finished, (np.array([1500.0, 2500.0]), np.array([0.0, 1.0]))], n_points=3)
    np.testing.assert_array_equal(steps, [1500, 2000, 2500])
    np.testing.assert_allclose(values[1], [0, 0.5, 1])


def test_logged_values_are_read_at_or_before_a_step():
    curve = (np.array([100.0, 300.0]), np.array([1.0, 2.0]))
    assert [plot.value_at(curve, step) for step in (300, 299, 1000)] == [2.0, 1.0, 2.0]
    assert np.isnan(plot.value_at(curve, 99)) and np.isnan(plot.value_at(None, 100))


def test_step_ticks_read_as_budgets():
    assert [plot.steps_label(steps) for steps in (0, 500, 15_000, 150_000, 640_000, 1_500_000)] == [
        "0", "500", "15k", "150k", "640k", "1.5M"
    ]  # fmt: skip


def test_hierarchical_metrics_from_a_benchmark_csv(tmp_path):
    """The committed CSV of a benchmark draws the same figure as the run folders it came from."""
    csv = tmp_path / "bench.csv"
    csv.write_text(
        "env,algo,seed,timesteps,success,subgoal_distance,low_value\n"
        "E-v0,dipper,0,1000,0.0,0.4,-30.0\nE-v0,dipper,0,2000,1.0,0.2,-20.0\n"
        "E-v0,dipper,1,1000,0.0,0.6,-40.0\nE-v0,dipper,1,2000,0.0,0.4,-30.0\n"
        "E-v0,sac,0,1000,0.0,,\nE-v0,sac,0,2000,0.0,,\n"
    )
    curves = plot.benchmark_csv_curves(csv)
    assert [list(values) for _, values in curves("E-v0", "dipper", "rollout/low_value")] == [[-30.0, -20.0], [-40.0, -30.0]]
    assert curves("E-v0", "sac", "rollout/subgoal_distance") == []
    figure = plot.draw_hierarchical_metrics(curves, ["dipper", "sac"], ["E-v0"])
    distance_axis, value_axis = figure.axes[:2]
    assert [line.get_label() for line in distance_axis.get_lines()] == ["DIPPER"]
    np.testing.assert_allclose(value_axis.get_lines()[0].get_ydata()[[0, -1]], [-35.0, -25.0])
    # Rows from several CSVs, with legend names of their own.
    other = tmp_path / "other.csv"
    other.write_text("env,algo,seed,timesteps,success,subgoal_distance,low_value\nE-v0,dipper-own,0,1000,1.0,0.1,-5.0\n")
    both = plot.benchmark_csv_curves(csv, other)
    figure = plot.draw_hierarchical_metrics(both, ["dipper", "dipper-own"], ["E-v0"], lambda name: f"{name}!")
    assert [line.get_label() for line in figure.axes[0].get_lines()] == ["dipper!", "dipper-own!"]


def test_training_success_reads_every_part_of_a_paused_run_in_step_order(tmp_path):
    from tests.tools.test_benchmark import write_monitor

    write_monitor(tmp_path / "part_1", [100, 100], [0, 1])
    write_monitor(tmp_path / "part_2", [100], [0])
    write_monitor(tmp_path, [50], [1])
    steps, success = plot.training_success_curve(tmp_path, window=2)
    np.testing.assert_array_equal(steps, [100, 200, 300, 350])
    np.testing.assert_allclose(success, [0.0, 0.5, 0.5, 0.5])
    assert plot.training_success_curve(tmp_path / "part_1" / "missing") is None


def line_pixels(ax, line) -> int:
    """How many pixels inside the panel have the line's colour (its band is lighter, alpha 0.2; the legend is below)."""
    ax.figure.canvas.draw()
    image = np.asarray(ax.figure.canvas.buffer_rgba())[..., :3].astype(int)
    box = ax.get_window_extent()
    panel = image[image.shape[0] - int(box.y1) : image.shape[0] - int(box.y0), int(box.x0) : int(box.x1)]
    return int((np.abs(panel - np.array(matplotlib.colors.to_rgb(line.get_color())) * 255).max(axis=-1) < 8).sum())


def test_a_series_of_one_point_is_drawn_with_a_marker():
    one_evaluation = [(np.array([1000.0]), np.array([0.5])), (np.array([1000.0]), np.array([0.7]))]
    fig = plot.draw_success({"MazeA-v0": {"dipper": one_evaluation, "sac": [(STEPS, STEPS / STEPS[-1])]}})
    single, several = fig.axes[0].get_lines()
    np.testing.assert_allclose(single.get_ydata(), [0.6])
    assert single.get_marker() == "o" and several.get_marker() == "None"
    assert line_pixels(fig.axes[0], single) > 20

    def curves(env_id, algo, key):
        return [(np.array([1000.0]), np.array([0.25]))]

    fig = plot.draw_hierarchical_metrics(curves, ["dipper"], ["MazeA-v0"])
    assert all(ax.get_lines()[0].get_marker() == "o" for ax in fig.axes)
    assert all(line_pixels(ax, ax.get_lines()[0]) > 20 for ax in fig.axes)
