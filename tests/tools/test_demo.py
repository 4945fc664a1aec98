"""`make demo` (zoo_scripts/demo.py) at a tiny budget: it trains, saves, plots and says who acted."""

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.test_files import truncate

REPO = Path(__file__).resolve().parents[2]


# Slow: the maze entry's label budget (50,000 pairs) labels and trains on many pairs per option even at a tiny budget
# (8 minutes for 2,400 steps on a loaded 2-core machine).
@pytest.mark.slow
def test_demo_trains_and_reports_the_model_and_its_policy_alone(tmp_path):
    command = [sys.executable, str(REPO / "zoo_scripts" / "demo.py"), "--output-dir", str(tmp_path), "--n-timesteps", "2400"]
    command += ["--eval-freq", "1200", "--eval-episodes", "1", "--final-episodes", "2"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    report = re.search(
        r"success over 2 episodes: (\S+) as trained \(the planner proposed (\d+)% of the subgoals, the preference-trained "
        r"policy the rest\); (\S+) with the policy alone \(planner off\)",
        done.stdout,
    )
    assert report, done.stdout
    assert 0 <= float(report[1]) <= 1 and 0 <= int(report[2]) <= 100 and 0 <= float(report[3]) <= 1
    assert (tmp_path / "success_curve.png").stat().st_size > 0 and (tmp_path / "dipper_point_maze.zip").is_file()


def test_the_success_curve_of_a_damaged_evaluation_record_is_an_error_naming_it(tmp_path):
    """A record cut short failed with a BadZipFile naming no file."""
    from zoo_scripts import demo

    record, figure = tmp_path / "evaluations.npz", tmp_path / "success_curve.png"
    success = np.array([[0.0, 1.0], [1.0, 1.0]])
    np.savez(record, timesteps=np.array([1200, 2400]), results=success - 1, ep_lengths=np.full((2, 2), 50), successes=success)
    demo.plot_success_curve(record, figure)
    assert figure.stat().st_size > 0
    figure.unlink()
    truncate(record)
    with pytest.raises(ValueError, match=r"evaluations\.npz: not a complete npz archive.* run the demo again"):
        demo.plot_success_curve(record, figure)
    assert not figure.exists()
