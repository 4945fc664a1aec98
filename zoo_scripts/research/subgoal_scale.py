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
on the Fetch object tasks), and their offset from the goal along the way still to go, from the achieved goal to the goal
(``beyond_goal``: positive past the goal, negative short of it), across that way (``beside_way``), and the length of
their mean offset from the goal (``offset_bias``: about ``subgoal_to_goal`` when every subgoal is moved alike, whatever
the state, near 0 when the offsets cancel; all in world units); it writes them as ``subgoal_scale.json`` in the zoo run
folder; with ``--csv``, one row per model and case; with ``--checkpoints``, every checkpoint the run kept too.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
from pathlib import Path

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")

from sb3_dipper.common.hierarchical import HierarchicalAlgorithm
from sb3_dipper.dipper import DIPPER
from sb3_dipper.raps import RAPS

# Run as a script, this file's folder is on the path; the scripts' folder above it holds the modules it shares.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from configs import evaluate, measure_runs, trained_run

DEFAULT_SCALES = (0.25, 0.5, 0.75, 1.0)
# The episodes' starts are drawn from this seed, the same in every case (paired comparisons), as planner_share.py's.
EVALUATION_SEED = 20_000


def move_proposals(model: HierarchicalAlgorithm, scale: float, rng: np.random.Generator | None = None) -> dict[str, list]:
    """Every subgoal ``model`` decides from now on moved to ``goal + scale * (subgoal - goal)`` (in world units), and
    with ``rng`` turned in a uniformly random direction at the same distance from the goal. Returns the lists it fills
    as the model decides: each final subgoal's offset from the goal (``offset``, a vector), its part along the way still
    to go, from the achieved goal to the goal (``beyond_goal``: positive past the goal, negative short of it), and its
    length across that way (``beside_way``), in world units."""
    assert model.subgoal_space is not None
    space, decide = model.subgoal_space, model._high_level_actions
    offsets_seen: dict[str, list] = {"offset": [], "beyond_goal": [], "beside_way": []}

    def moved(observation: dict[str, np.ndarray], deterministic: bool) -> np.ndarray:
        goals = space.to_world(model._subgoal_actions(observation["desired_goal"]))
        offsets = space.to_world(decide(observation, deterministic)) - goals
        if rng is not None:
            directions = rng.normal(size=offsets.shape)
            directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
            offsets = directions * np.linalg.norm(offsets, axis=-1, keepdims=True)
        subgoals = space.to_world(space.to_unit(goals + scale * offsets))
        way = goals - space.to_world(model._subgoal_actions(observation["achieved_goal"], "achieved_goal"))
        way /= np.maximum(np.linalg.norm(way, axis=-1, keepdims=True), 1e-8)
        final_offsets = subgoals - goals
        along = np.sum(final_offsets * way, axis=-1)
        offsets_seen["offset"] += list(final_offsets)
        offsets_seen["beyond_goal"] += along.tolist()
        offsets_seen["beside_way"] += np.linalg.norm(final_offsets - along[:, None] * way, axis=-1).tolist()
        return space.to_unit(subgoals)

    model._high_level_actions = moved  # type: ignore[method-assign]
    return offsets_seen


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
        model, env = trained_run(run, algo, env_id, seed=EVALUATION_SEED, model_file=model_file)
        if not isinstance(model, HierarchicalAlgorithm) or isinstance(model, RAPS) or model.subgoal_space is None:
            raise ValueError(
                f"{run}: the model is a {type(model).__name__}, whose higher level proposes no subgoals "
                "(--algo names a DIPPER, HIER, PIPER, SAGA or HAC entry)"
            )
        if isinstance(model, DIPPER):
            model.planner.graph = None
        steps = model.num_timesteps
        offsets = move_proposals(model, scale, np.random.default_rng(0) if random_direction else None)
        results[name] = evaluate(model, env, n_episodes)
        results[name].update(
            beyond_goal=float(np.mean(offsets["beyond_goal"])),
            beside_way=float(np.mean(offsets["beside_way"])),
            offset_bias=float(np.linalg.norm(np.mean(offsets["offset"], axis=0))),
        )
        env.close()
    return steps, results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", type=Path, nargs="+", help="zoo run folders (logs/dipper/<env>_<n>) holding <env>.zip")
    parser.add_argument("--algo", default="dipper", help="zoo name of the models' algorithm (a hierarchical entry)")
    parser.add_argument("--env", help="task (default: each run folder's name without its _<n>)")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument(
        "--scales", type=float, nargs="+", default=list(DEFAULT_SCALES), help="fractions of the way from the goal (0-1)"
    )
    parser.add_argument("--random", action="store_true", help="also turn each offset in a random direction")
    parser.add_argument("--csv", type=Path, help="also write every run's results to this CSV")
    parser.add_argument("--checkpoints", action="store_true", help="also measure every rl_model_<steps>_steps.zip of a run")
    args = parser.parse_args()
    outside = [scale for scale in args.scales if not 0.0 <= scale <= 1.0]
    if outside:
        parser.error(f"--scales {outside}: each scale is a fraction of the way from the goal to the subgoal, in [0, 1]")
    columns = ("subgoals", "success", "subgoal_to_goal", "subgoal_to_achieved", "beyond_goal", "beside_way", "offset_bias")
    measure_scaled = functools.partial(measure, scales=tuple(args.scales), random_directions=args.random)
    measure_runs(parser, args, measure_scaled, "subgoal_scale.json", columns)


if __name__ == "__main__":
    main()
