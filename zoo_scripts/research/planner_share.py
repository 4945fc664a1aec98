"""Who proposes the subgoals: the planner or the preference-trained policy? A trained DIPPER, four ways (three without
a planner).

    python zoo_scripts/research/planner_share.py logs/dipper/PointMazeFourRooms-v0_1
    python zoo_scripts/research/planner_share.py runs/*/seed_*/dipper/PointMazeFourRooms-v0_1 --csv planner_share.csv
    python zoo_scripts/research/planner_share.py runs/p9/switches/seed_1/dipper/FetchPushFixed-v0_1 --checkpoints \
        --csv curve.csv
    python zoo_scripts/research/planner_share.py runs/p9/default/seed_0/dipper_nov/FetchPushFixed-v0_1 --algo dipper_nov \
        --checkpoints

With the subgoal planner (``planner_kwargs`` ``mode="subgoal"``) the planner over achieved states replaces the higher
policy's proposal wherever its graph knows a path to the goal, so the success of the model as trained can be the
planner's and the lower level's alone. The script evaluates the model (deterministic episodes) as trained, with the
higher policy reset to untrained weights (if the success holds, the preference-trained policy does not matter where the
planner decides), with the planner off (the preference-trained policy alone) and with the env's goal as every subgoal
(the lower level alone: what the hierarchy adds is measured against it). For each it prints the episode success and the
share of higher-level decisions the planner made, and writes them as ``planner_share.json`` in the zoo run folder; with
``--csv``, also one CSV row per run, model and case. With ``--checkpoints`` it also measures every checkpoint the run
kept (``rl_model_<steps>_steps.zip``, from ``benchmark.py learning --save-freq``), so the four cases can be followed
over training; each checkpoint of a run with ``VecNormalize`` is evaluated with the observation statistics it trained
with (the model's own copy).

A DIPPER without the planner (planner mode ``"off"`` or ``"waypoint"``: the paper's DIPPER, DIPPER-No-V) gets the three
cases that do not need it: as trained (its policy alone), with the higher policy untrained and with the env's goal as
every subgoal; whether its success is the preference-trained policy's or the lower level's alone. So do the baselines
with a learned lower level (``--algo hier``, ``piper``, ``saga``, ``hac``): whether their trained higher level adds to
their lower level's success or takes from it.

    python zoo_scripts/research/planner_share.py runs/p9/VARIANT/seed_0/hier/FrankaKitchenMicrowaveBurner-v0_1 --algo hier

``--sampled`` adds two cases that act as training collects (without its uniformly random subgoals): ``sampled``, both
levels sampling their policies, and ``greedy_lower``, the higher level sampling while the lower level acts
deterministically (a ``greedy_episode_prob`` episode). Where the deterministic model succeeds and ``sampled`` never
does, the training episodes all fail alike and a preference label has nothing to tell apart.

    python zoo_scripts/research/planner_share.py runs/p9/default/seed_0/dipper/FrankaKitchenMicrowaveBurner-v0_1 --sampled
"""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import torch as th

from sb3_dipper.common.hierarchical import HierarchicalAlgorithm
from sb3_dipper.dipper import DIPPER
from sb3_dipper.dipper.policies import FlooredStdActor

# Run as a script, this file's folder is on the path; the scripts' folder above it holds the modules it shares.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from configs import evaluate, measure_runs, measurement_parser, trained_hierarchy

CASES = ("as_trained", "untrained_policy", "policy_alone", "lower_level_alone")
# Without the subgoal planner the model as trained is its policy alone.
CASES_WITHOUT_PLANNER = tuple(case for case in CASES if case != "policy_alone")
# With --sampled: the model acting as training collects, both levels sampling or the lower level greedy.
SAMPLED_CASES = ("sampled", "greedy_lower")


def case_settings(case: str) -> dict[str, bool]:
    """How :func:`evaluate` runs ``case`` (the untrained policy and the planner off are set on the model instead)."""
    return {
        "goal_as_subgoal": case == "lower_level_alone",
        "sample_higher": case in SAMPLED_CASES,
        "sample_lower": case == "sampled",
    }


def reset_higher_policy(model: HierarchicalAlgorithm, seed: int) -> None:
    """Every network of the higher policy back to freshly initialised weights (drawn from ``seed``); a goal-anchored
    DIPPER policy back to proposing the goal, as it starts."""
    th.manual_seed(seed)
    for module in model.policy.modules():
        reset = getattr(module, "reset_parameters", None)
        if callable(reset):
            reset()
    for module in model.policy.modules():
        if isinstance(module, FlooredStdActor):
            module.start_at_the_anchor()


def measure(
    run: Path, algo: str, env_id: str, n_episodes: int, model_file: Path | None = None, sampled: bool = False
) -> tuple[int, dict[str, dict[str, float]]]:
    """Every case of :data:`CASES` (of :data:`CASES_WITHOUT_PLANNER` for a model without the subgoal planner, and
    :data:`SAMPLED_CASES` with ``sampled``) on a fresh copy of the run's model (or of ``model_file``), and the
    primitive steps that model had trained."""
    results: dict[str, dict[str, float]] = {}
    model, env = trained_hierarchy(run, algo, env_id, model_file)
    steps = model.num_timesteps
    has_planner = isinstance(model, DIPPER) and model.planner.mode == "subgoal"
    cases = (CASES if has_planner else CASES_WITHOUT_PLANNER) + (SAMPLED_CASES if sampled else ())
    for case in cases:
        if results:  # every case after the first on a fresh copy: a case changes the model
            model, env = trained_hierarchy(run, algo, env_id, model_file)
        if case == "untrained_policy":
            reset_higher_policy(model, seed=0)
        if case == "policy_alone":  # only a DIPPER with the planner has this case
            assert isinstance(model, DIPPER)
            model.planner.graph = None
        results[case] = evaluate(model, env, n_episodes, **case_settings(case))
        env.close()
    return steps, results


def main() -> None:
    parser = measurement_parser(__doc__, episodes=50)
    parser.add_argument("--sampled", action="store_true", help="also act as training collects: " + ", ".join(SAMPLED_CASES))
    args = parser.parse_args()
    measure_sampled = functools.partial(measure, sampled=args.sampled)
    columns = ("case", "success", "planned_share", "subgoal_to_goal", "subgoal_to_achieved")
    measure_runs(parser, args, measure_sampled, "planner_share.json", columns)


if __name__ == "__main__":
    main()
