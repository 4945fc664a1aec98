"""How often a trained DIPPER's labels agree with oracles of the true progress, the maze's way round the walls included.

    python zoo_scripts/research/label_agreement.py runs/f58/anchored-goalep/seed_0/dipper/FetchFourRoomMaze-v0_1
    python zoo_scripts/research/label_agreement.py RUN --steps 6000 --pairs 4000 --csv agreement.csv

A higher level learns only what its labels tell apart. For each model the script collects ``--steps`` primitive steps
as training collects them (exploration and goal episodes included, no update), draws ``--pairs`` pairs with the model's
own pair sampler and labels them with its own labeller, as a training round does. It then asks three oracles which
trajectory of each pair made more progress: ``end`` (ended nearer the pair's goal, in a straight line), ``gain`` (came
nearer the goal than it started by more) and, on the Fetch mazes, ``path`` (ended nearer the goal along the free cells,
:meth:`~sb3_dipper.envs.fetch.MazeGeometry.path_distances`: the straight line prefers a gripper pressed against the
wall nearest the goal, the path the one nearer the gate). For the pairs that keep each trajectory's own goal
(``own_goals``), those that share a hindsight goal (``shared_goal``) and all of them: the group's ``share`` of the
pairs, the ``tie_share`` of the model's labels, and each oracle's ``<oracle>_agreement`` with the labels over the pairs
both decide (NaN where none; ``path`` NaN off the mazes) and ``<oracle>_decided`` (the share of the group's pairs the
oracle decides). It writes them as ``label_agreement.json`` in the zoo run folder; with ``--csv``, one row per model
and group; with ``--checkpoints``, every checkpoint the run kept too.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np

from sb3_dipper.common.preferences import (
    TrajectoryPairs,
    final_path_distances,
    labels_from_scores,
    progress_gain_labels,
    progress_labels,
)
from sb3_dipper.envs.fetch import MazeGeometry

# Run as a script, this file's folder is on the path; the scripts' folder above it holds the modules it shares.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from configs import collected_dipper, measure_pair_runs

ORACLES = ("end", "gain", "path")
COLUMNS = ("group", "share", "tie_share", *(f"{oracle}_{what}" for oracle in ORACLES for what in ("agreement", "decided")))


def label_agreement(
    pairs: TrajectoryPairs, labels: np.ndarray, path_distances: np.ndarray | None = None
) -> dict[str, dict[str, float]]:
    """Per group of pairs (``all``, ``own_goals``, ``shared_goal``): its share of the pairs, the share of ``labels``
    that are ties, and for each oracle its agreement with the labels over the pairs both decide and the share of the
    group's pairs it decides (NaN for the ``path`` oracle without ``path_distances``, ``(2, B)``)."""
    oracles = {"end": progress_labels(pairs), "gain": progress_gain_labels(pairs)}
    if path_distances is not None:
        oracles["path"] = labels_from_scores(-path_distances)
    assert pairs.shared_goal is not None, "pairs drawn from a trajectory buffer say which share a hindsight goal"
    decided = ~np.isnan(labels) & (labels != 0.5)  # NaN: a label people have not given yet
    results = {}
    for group, members in (
        ("all", np.ones_like(decided)),
        ("own_goals", ~pairs.shared_goal),
        ("shared_goal", pairs.shared_goal),
    ):
        row = {
            "share": float(members.mean()),
            "tie_share": float(np.mean(labels[members] == 0.5)) if members.any() else float("nan"),
        }
        for oracle in ORACLES:
            answers = oracles.get(oracle)
            if answers is None or not members.any():
                row[f"{oracle}_agreement"] = row[f"{oracle}_decided"] = float("nan")
                continue
            counted = members & decided & (answers != 0.5)
            agreement = np.mean(labels[counted] == answers[counted]) if counted.any() else float("nan")
            row[f"{oracle}_agreement"] = float(agreement)
            row[f"{oracle}_decided"] = float(np.mean(answers[members] != 0.5))
        results[group] = row
    return results


def measure(
    run: Path, algo: str, env_id: str, n_steps: int, n_pairs: int, model_file: Path | None = None
) -> tuple[int, dict[str, dict[str, float]]]:
    """Collect ``n_steps`` steps with the run's model (or ``model_file``) as training does, without updates, draw and
    label ``n_pairs`` pairs as a training round does; returns the model's primitive steps and :func:`label_agreement`."""
    model, steps = collected_dipper(run, algo, env_id, n_steps, model_file, seed=30_000)
    pipeline = model.preference_pipeline
    assert pipeline.labeler is not None
    pairs = pipeline.sampler.sample(model.trajectory_buffer, n_pairs, np.random.default_rng(0))
    labels = np.asarray(pipeline.labeler.label(pairs), dtype=np.float32)
    env = model.get_env()
    assert env is not None
    maze = env.get_attr("maze")[0] if env.has_attr("maze") else None
    path_distances = final_path_distances(pairs, maze.path_distances) if isinstance(maze, MazeGeometry) else None
    return steps, label_agreement(pairs, labels, path_distances)


def main() -> None:
    measure_pair_runs(__doc__, measure, "label_agreement.json", COLUMNS)


if __name__ == "__main__":
    main()
