"""How a trained DIPPER's tied labels are answered when the two trajectories of a pair start apart.

    python zoo_scripts/research/tie_answers.py runs/f56/anchored-goalep/seed_0/dipper/FetchPush-v4_1
    python zoo_scripts/research/tie_answers.py RUN --checkpoints --steps 6000 --pairs 4000 --csv ties.csv
    python zoo_scripts/research/tie_answers.py RUN --matched-control-prob 0 --csv random-pairs.csv

On a task whose starts and goals are drawn at random, the two trajectories of a preference pair begin at different
distances from their goals. Where the primitive-in-the-loop labeller ties (neither trajectory, or both equally often,
reached the goal), ``preference_source="progress"`` prefers the trajectory that ended nearer the goal and
``"progress:gain"`` the one whose distance fell more; both can depend on where each began rather than on its subgoals.
For each model the script collects ``--steps`` primitive steps as training collects them (its exploration and goal
episodes included, no update), draws ``--pairs`` pairs with the model's own pair sampler, labels them with its
primitive-in-the-loop labeller, and reports, for the tied pairs, how often each answer prefers the trajectory that
began nearer its goal (0.5: independent of the start; 1: decided by it), separately for pairs that keep each
trajectory's own goal (``own_goals``: a goal-driven contrast pair, or a pair not relabelled) and pairs that share one
(``shared_goal``: hindsight-relabelled), and how far apart the two trajectories of a pair started.
``--matched-control-prob`` draws the pairs with that ``switch_kwargs`` ``matched_control_prob`` instead of the model's
own (0: pairs drawn at random; 1: each a trajectory of the policy's and the goal-driven one that started nearest it).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import torch as th

from sb3_dipper.common.preferences import (
    TrajectoryPairs,
    TrajectoryPairSampler,
    labels_from_scores,
    progress_gain_labels,
    progress_labels,
    start_gaps,
    start_goal_distances,
)

# Run as a script, this file's folder is on the path; the scripts' folder above it holds the modules it shares.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from configs import collected_dipper, measure_runs, pair_measurement_parser, parsed_pair_arguments

COLUMNS = ("group", "share", "tie_share", "start_gap", "end_prefers_nearer_start", "gain_prefers_nearer_start")


def tie_answers(pairs: TrajectoryPairs, script_labels: np.ndarray) -> dict[str, dict[str, float]]:
    """Per group of pairs (``all``, ``own_goals``, ``shared_goal``): its share of the pairs, its share of ties, how far
    apart its pairs' trajectories started on average (:func:`~sb3_dipper.common.preferences.start_gaps`), and how
    often the end's and the gain's answers to its ties prefer the trajectory that began nearer its goal (NaN without
    a tie whose trajectories began at different distances)."""
    ties = script_labels == 0.5
    began_nearer = labels_from_scores(-start_goal_distances(pairs))
    gaps = start_gaps(pairs)
    answers = {"end": progress_labels(pairs), "gain": progress_gain_labels(pairs)}
    assert pairs.shared_goal is not None, "pairs drawn from a trajectory buffer say which share a hindsight goal"
    own_goals = ~pairs.shared_goal
    results = {}
    for group, members in (("all", np.ones_like(ties)), ("own_goals", own_goals), ("shared_goal", ~own_goals)):
        counted = np.flatnonzero(members & ties & (began_nearer != 0.5))
        results[group] = {
            "share": float(members.mean()),
            "tie_share": float(ties[members].mean()) if members.any() else float("nan"),
            "start_gap": float(gaps[members].mean()) if members.any() else float("nan"),
            **{
                f"{name}_prefers_nearer_start": float(np.mean(labels[counted] == began_nearer[counted]))
                if counted.size
                else float("nan")
                for name, labels in answers.items()
            },
        }
    return results


def measure(
    run: Path,
    algo: str,
    env_id: str,
    n_steps: int,
    n_pairs: int,
    model_file: Path | None = None,
    matched_control_prob: float | None = None,
) -> tuple[int, dict[str, dict[str, float]]]:
    """Collect ``n_steps`` steps with the run's model (or ``model_file``) as training does, without updates, and
    answer the ties of ``n_pairs`` pairs drawn from them (with the model's own pair sampler, or with its
    ``matched_control_prob`` set to the one given); returns the model's primitive steps and :func:`tie_answers`."""
    model, steps = collected_dipper(run, algo, env_id, n_steps, model_file, seed=30_000)
    pipeline = model.preference_pipeline
    assert pipeline.labeler is not None
    if matched_control_prob is not None:
        assert isinstance(pipeline.sampler, TrajectoryPairSampler)  # DIPPER's
        pipeline.sampler.matched_control_prob = matched_control_prob
    pairs = pipeline.sampler.sample(model.trajectory_buffer, n_pairs, np.random.default_rng(0))
    script = getattr(pipeline.labeler, "script", None) or pipeline.labeler
    return steps, tie_answers(pairs, np.asarray(script.label(pairs)))


def main() -> None:
    parser = pair_measurement_parser(__doc__)
    parser.add_argument(
        "--matched-control-prob",
        type=float,
        help="draw the pairs with this switch_kwargs matched_control_prob instead of the model's own",
    )
    args = parsed_pair_arguments(parser)
    if args.matched_control_prob is not None and not 0.0 <= args.matched_control_prob <= 1.0:
        parser.error(f"--matched-control-prob must be in [0, 1], got {args.matched_control_prob}")
    th.set_num_threads(1)

    def measure_model(run: Path, algo: str, env_id: str, _: int, model_file: Path | None) -> tuple[int, dict]:
        return measure(run, algo, env_id, args.steps, args.pairs, model_file, args.matched_control_prob)

    measure_runs(parser, args, measure_model, "tie_answers.json", COLUMNS)


if __name__ == "__main__":
    main()
