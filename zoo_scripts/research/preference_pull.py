"""Which way does a trained DIPPER's higher-level loss move its subgoals, and which of its pairs move them?

    python zoo_scripts/research/preference_pull.py runs/f56/anchored-goalep/seed_0/dipper/FetchPush-v4_1
    python zoo_scripts/research/preference_pull.py RUN --steps 6000 --pairs 4000 --csv pull.csv

Where the preference-trained policy's subgoals fall short of the goal, along the way from the achieved goal to it, the
loss that trained it pulls them there. For each model the script collects ``--steps`` primitive steps as training
collects them (exploration and goal episodes included, no update), draws ``--pairs`` pairs with the model's own pair
sampler and labels them with its own labeller, as a training round does. It then evaluates the model's higher-level loss
on all of them as one batch (:meth:`~sb3_dipper.dipper.DIPPER.high_level_loss`) and takes, at every real step of every
pair, the force the log-likelihood terms (the DPO term and, where it is on, the preferred side's NLL) put on the policy's
mean subgoal: minus the loss's gradient with respect to the mean, in world units. Its component along the way still to
go, from the step's achieved goal to the goal the policy sees in the pair (a hindsight goal where the pair shares one),
says whether the loss pulls subgoals back toward the achieved goal (negative) or on past the goal (positive).

The pairs are split by how the sampler drew them: ``contrast`` (a goal-driven trajectory and one of the policy's, each
with its own goal), ``own_goals`` (two trajectories of the same driver, each with its own goal) and ``shared_goal``
(both given a hindsight goal achieved by one of them). For each group: its ``share`` of the pairs and ``tie_share``;
where the policy's mean subgoals at the pairs' steps lie from the pair's goal along the way (``policy_along``: mean
signed distance, negative short of the goal), and where the preferred and the rejected trajectories' stored subgoals
lie (``preferred_along``, ``rejected_along``, over the strict pairs: the loss draws the mean toward the first and
pushes it from the second); how far from the pair's goal each lies (``policy_to_goal``, ``preferred_to_goal``,
``rejected_to_goal``);
and the group's part of the total force along the way (``pull_along``, a fraction of the summed force lengths of all
groups, so the groups' values add up to the whole batch's) and its part of the force lengths (``pull_share``). The
``all`` row is the whole batch. It writes them as ``preference_pull.json`` in the zoo run folder; with ``--csv``, one
row per model and group; with ``--checkpoints``, every checkpoint the run kept too.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import torch as th

from sb3_dipper.common.preferences import TrajectoryPairs
from sb3_dipper.common.subgoals import ElementSubgoalSpace
from sb3_dipper.dipper import DIPPER

# Run as a script, this file's folder is on the path; the scripts' folder above it holds the modules it shares.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from configs import collected_dipper, goal_and_way, measure_pair_runs

COLUMNS = (
    "pairs",
    "share",
    "tie_share",
    "policy_along",
    "preferred_along",
    "rejected_along",
    "policy_to_goal",
    "preferred_to_goal",
    "rejected_to_goal",
    "pull_along",
    "pull_share",
)


def pair_groups(pairs: TrajectoryPairs) -> dict[str, np.ndarray]:
    """``(B,)`` membership of every group, from what the sampler recorded of each pair (``all`` first)."""
    assert pairs.shared_goal is not None and pairs.goal_driven is not None, "pairs drawn by a trajectory pair sampler"
    contrast = ~pairs.shared_goal & (pairs.goal_driven[0] != pairs.goal_driven[1])
    return {
        "all": np.ones(len(pairs), dtype=bool),
        "contrast": contrast,
        "own_goals": ~pairs.shared_goal & ~contrast,
        "shared_goal": pairs.shared_goal,
    }


def mean_subgoal_forces(model: DIPPER, pairs: TrajectoryPairs) -> tuple[np.ndarray, np.ndarray]:
    """The policy's mean subgoal at each real step of labelled ``pairs`` and minus the gradient of ``model``'s
    higher-level loss on them (one batch) with respect to it, in world units, ``(2, B, T, d)`` each (0 at the padding).

    Only the log-likelihood terms reach the mean evaluated here (a goal-anchored policy's leash and the ``reparam``
    value term evaluate the actor again, and are left out)."""
    assert model.subgoal_space is not None
    actor = model.policy.actor
    evaluated = actor.get_action_dist_params
    means: list[th.Tensor] = []

    def keeping_the_mean(obs):  # type: ignore[no-untyped-def]
        mean, log_std, kwargs = evaluated(obs)
        mean.retain_grad()
        means.append(mean)
        return mean, log_std, kwargs

    actor.get_action_dist_params = keeping_the_mean  # type: ignore[method-assign]
    try:
        loss, _ = model.high_level_loss(pairs)
        actor.optimizer.zero_grad()
        loss.backward()
    finally:
        del actor.get_action_dist_params
    mean = means[0]
    assert mean.grad is not None
    # The world subgoal is low + (tanh(mean) + 1) / 2 * span per entry: its derivative is span / 2 * (1 - tanh^2).
    span = model.subgoal_space.to_world(np.ones(mean.shape[-1])) - model.subgoal_space.to_world(-np.ones(mean.shape[-1]))
    unit_mean = np.tanh(mean.detach().numpy())
    slope = 0.5 * span * (1.0 - unit_mean**2)
    subgoals, forces = (np.zeros((*pairs.mask.shape, mean.shape[-1])) for _ in range(2))
    subgoals[pairs.mask] = model.subgoal_space.to_world(unit_mean)
    forces[pairs.mask] = -mean.grad.numpy() * slope
    return subgoals, forces


def preference_pull(model: DIPPER, pairs: TrajectoryPairs) -> dict[str, dict[str, float]]:
    """Per group of :func:`pair_groups`, the columns of :data:`COLUMNS` for labelled ``pairs`` (see the module)."""
    assert model.subgoal_space is not None
    goals, ways = goal_and_way(model, pairs.observations)
    stored_offsets = model.subgoal_space.to_world(model._pair_actions(pairs)) - goals
    mean_subgoals, forces = mean_subgoal_forces(model, pairs)
    # Per step (2, B, T): signed distance from the pair's goal along the way, and distance from it.
    stored_along, stored_to_goal = np.sum(stored_offsets * ways, axis=-1), np.linalg.norm(stored_offsets, axis=-1)
    policy_along = np.sum((mean_subgoals - goals) * ways, axis=-1)
    policy_to_goal = np.linalg.norm(mean_subgoals - goals, axis=-1)
    force_along = np.sum(forces * ways, axis=-1).sum(axis=(0, 2))  # per pair
    force_length = np.linalg.norm(forces, axis=-1).sum(axis=(0, 2))
    total_length = max(float(force_length.sum()), 1e-12)
    strict = pairs.labels != 0.5
    preferred_side = np.where(pairs.labels == 1.0, 0, 1)
    index = np.arange(len(pairs))
    results = {}
    for group, members in pair_groups(pairs).items():
        chosen = members & strict

        def side_mean(values: np.ndarray, side: np.ndarray, chosen: np.ndarray = chosen) -> float:
            steps = pairs.mask[side[chosen], index[chosen]]
            return float(values[side[chosen], index[chosen]][steps].mean()) if steps.any() else float("nan")

        def both_sides_mean(values: np.ndarray, members: np.ndarray = members) -> float:
            steps = pairs.mask[:, members]
            return float(values[:, members][steps].mean()) if steps.any() else float("nan")

        results[group] = {
            "share": float(members.mean()),
            "tie_share": float((~strict[members]).mean()) if members.any() else float("nan"),
            "policy_along": both_sides_mean(policy_along),
            "preferred_along": side_mean(stored_along, preferred_side),
            "rejected_along": side_mean(stored_along, 1 - preferred_side),
            "policy_to_goal": both_sides_mean(policy_to_goal),
            "preferred_to_goal": side_mean(stored_to_goal, preferred_side),
            "rejected_to_goal": side_mean(stored_to_goal, 1 - preferred_side),
            "pull_along": float(force_along[members].sum()) / total_length,
            "pull_share": float(force_length[members].sum()) / total_length,
        }
    return results


def measure(
    run: Path, algo: str, env_id: str, n_steps: int, n_pairs: int, model_file: Path | None = None
) -> tuple[int, dict[str, dict[str, float]]]:
    """Collect ``n_steps`` steps with the run's model (or ``model_file``) as training does, without updates, label
    ``n_pairs`` pairs drawn from them as a training round does, and return the model's primitive steps and
    :func:`preference_pull`."""
    model, steps = collected_dipper(run, algo, env_id, n_steps, model_file)
    if isinstance(model.subgoal_space, ElementSubgoalSpace):
        raise ValueError(f"{run}: the model's subgoals are task elements, with no way toward the goal to measure along")
    pipeline = model.preference_pipeline
    assert pipeline.labeler is not None
    pairs = pipeline.sampler.sample(model.trajectory_buffer, n_pairs, np.random.default_rng(0))
    pairs.labels = pipeline.labeler.label(pairs)
    if np.isnan(pairs.labels).any():
        raise ValueError(f"{run}: the model's labels come from people; the script needs a scripted labeller")
    return steps, preference_pull(model, pairs)


def main() -> None:
    measure_pair_runs(__doc__, measure, "preference_pull.json", COLUMNS)


if __name__ == "__main__":
    main()
