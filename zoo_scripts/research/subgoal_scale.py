"""Do the preference-trained policy's subgoals help, and by how much of them? A trained model with every subgoal its
higher policy decides moved part of the way back to the goal, or turned in a random direction.

    python zoo_scripts/research/subgoal_scale.py runs/f56/anchored-goalep/seed_0/dipper/FetchPush-v4_1 --episodes 50
    python zoo_scripts/research/subgoal_scale.py runs/*/seed_*/dipper/FetchPush-v4_1 --scales 0.5 1 --random \
        --csv scale.csv

Where DIPPER's own policy acting scores below its lower level driven by the goal, its subgoals cost success. This script
says whether they cost it by their direction or by their mere distance from the goal. It evaluates the model
(deterministic episodes, the same starts in every case) with the goal as every subgoal (case ``goal``) and, for every
scale ``s`` of ``--scales``, with each subgoal moved to ``g + s * (subgoal - g)``, ``g`` the env's goal (case ``policy
<s>``; ``policy 1`` is the policy alone); with ``--random``, also with the same offset from the goal turned in a
uniformly random direction (case ``random <s>``: as far from the goal, in no learnt direction). If the policy's success
falls steadily from the goal's as the scale grows, every step away from the goal costs; if the random directions cost as
much, the policy's direction carries nothing the lower level can use, and if they cost more, it carries something. A
subgoal planner, where the model has one, is off: the subject is the policy's own proposals. For each case the script
prints the episode success, how far the subgoals lie from the goal and from the achieved goal when deciding (the object,
on the Fetch object tasks), how far they fall short of the goal and past it along the way still to go (from the
achieved goal to the goal: ``short_of_goal``, ``past_goal``), how far beside that way (``beside_way``), and the length
of their mean offset from the goal (``offset_bias``: about ``subgoal_to_goal`` when every subgoal is moved alike,
whatever the state, near 0 when the offsets cancel; all means over the decisions, in world units); it writes them as
``subgoal_scale.json`` in the zoo run folder; with ``--csv``, one row per model and case; with ``--checkpoints``, every
checkpoint the run kept too.
"""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")

from sb3_dipper.common.hierarchical import HierarchicalAlgorithm
from sb3_dipper.common.subgoals import ElementSubgoalSpace
from sb3_dipper.dipper import DIPPER

# Run as a script, this file's folder is on the path; the scripts' folder above it holds the modules it shares.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from configs import evaluate, goal_and_way, measure_runs, measurement_parser, trained_hierarchy

DEFAULT_SCALES = (0.25, 0.5, 0.75, 1.0)


def move_proposals(model: HierarchicalAlgorithm, scale: float, rng: np.random.Generator | None = None) -> dict[str, list]:
    """Every subgoal ``model`` decides from now on moved to ``goal + scale * (subgoal - goal)`` (in world units), and
    with ``rng`` turned in a uniformly random direction at the same distance from the goal. Returns the lists it fills
    as the model decides, for :func:`offset_summary`: each final subgoal's offset from the goal (``offset``) and the
    unit vector of the way still to go, from the achieved goal to the goal (``way``), in world units."""
    assert model.subgoal_space is not None
    space, decide = model.subgoal_space, model._high_level_actions
    if isinstance(space, ElementSubgoalSpace):
        raise ValueError(
            "the model's subgoals are task elements, each done or at rest (ElementSubgoalSpace): a subgoal part of the "
            "way from the goal is not one of them, so its proposals cannot be moved"
        )
    seen: dict[str, list] = {"offset": [], "way": []}

    def moved(observation: dict[str, np.ndarray], deterministic: bool) -> np.ndarray:
        goals, way = goal_and_way(model, observation)
        offsets = space.to_world(decide(observation, deterministic)) - goals
        if rng is not None:
            directions = rng.normal(size=offsets.shape)
            directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
            offsets = directions * np.linalg.norm(offsets, axis=-1, keepdims=True)
        subgoals = space.to_world(space.to_unit(goals + scale * offsets))
        seen["offset"] += list(subgoals - goals)
        seen["way"] += list(way)
        return space.to_unit(subgoals)

    model._high_level_actions = moved  # type: ignore[method-assign]
    return seen


def offset_summary(offsets: np.ndarray, ways: np.ndarray) -> dict[str, float]:
    """Where subgoals lie from the goal, given their ``offsets`` from it and the unit ``ways`` still to go (one row per
    decision): the mean distance they fall short of the goal along the way (``short_of_goal``) and past it
    (``past_goal``), the mean distance beside the way (``beside_way``) and the length of the mean offset
    (``offset_bias``: as long as the offsets when every subgoal is moved alike, near 0 when they cancel)."""
    along = np.sum(offsets * ways, axis=-1)
    return {
        "short_of_goal": float(np.mean(np.maximum(-along, 0.0))),
        "past_goal": float(np.mean(np.maximum(along, 0.0))),
        "beside_way": float(np.mean(np.linalg.norm(offsets - along[:, None] * ways, axis=-1))),
        "offset_bias": float(np.linalg.norm(np.mean(offsets, axis=0))),
    }


def cases(scales: tuple[float, ...], random_directions: bool) -> dict[str, tuple[float, bool]]:
    """Every case's name and its ``(scale, random direction)``: the goal first, then the policy's and the random
    directions' at each scale."""
    named = {"goal": (0.0, False)}
    for scale in scales:
        named[f"policy {scale:g}"] = (scale, False)
        if random_directions:
            named[f"random {scale:g}"] = (scale, True)
    return named


def measure(
    run: Path,
    algo: str,
    env_id: str,
    n_episodes: int,
    model_file: Path | None = None,
    scales: tuple[float, ...] = DEFAULT_SCALES,
    random_directions: bool = False,
) -> tuple[int, dict[str, dict[str, float]]]:
    """Every case of :func:`cases` on a fresh copy of the model of ``run`` (or ``model_file``) with the same episode
    starts, and the primitive steps that model had trained."""
    results: dict[str, dict[str, float]] = {}
    steps = 0
    for name, (scale, random_direction) in cases(scales, random_directions).items():
        model, env = trained_hierarchy(run, algo, env_id, model_file)
        if isinstance(model, DIPPER):
            model.planner.graph = None
        steps = model.num_timesteps
        offsets = move_proposals(model, scale, np.random.default_rng(0) if random_direction else None)
        results[name] = evaluate(model, env, n_episodes)
        results[name].update(offset_summary(np.array(offsets["offset"]), np.array(offsets["way"])))
        env.close()
    return steps, results


def main() -> None:
    parser = measurement_parser(__doc__, episodes=50)
    parser.add_argument(
        "--scales", type=float, nargs="+", default=list(DEFAULT_SCALES), help="fractions of the way from the goal (0-1)"
    )
    parser.add_argument("--random", action="store_true", help="also turn each offset in a random direction")
    args = parser.parse_args()
    outside = [scale for scale in args.scales if not 0.0 <= scale <= 1.0]
    if outside:
        parser.error(f"--scales {outside}: each scale is a fraction of the way from the goal to the subgoal, in [0, 1]")
    columns = (
        "subgoals",
        "success",
        "subgoal_to_goal",
        "subgoal_to_achieved",
        "short_of_goal",
        "past_goal",
        "beside_way",
        "offset_bias",
    )
    measure_scaled = functools.partial(measure, scales=tuple(args.scales), random_directions=args.random)
    measure_runs(parser, args, measure_scaled, "subgoal_scale.json", columns)


if __name__ == "__main__":
    main()
