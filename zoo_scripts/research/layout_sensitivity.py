"""How much a trained higher policy's subgoal on the random Fetch mazes depends on the layout it is shown.

    python zoo_scripts/research/layout_sensitivity.py runs/f58/anchored-goalep/seed_0/dipper/FetchFourRoomMaze-v0_1
    python zoo_scripts/research/layout_sensitivity.py runs/f61/baselines/seed_0/hac/FetchFourRoomMaze-v0_1 --algo hac

On random layouts the way to the goal runs through the gates of the layout at hand, so a higher level that helps its
lower level round the walls proposes subgoals that change with the layout. The script draws ``--episodes`` unseen
episode starts (:data:`~configs.UNSEEN_EPISODES_SEED`), and for each start shows the model's deterministic higher
policy the same gripper position and goal in up to ``--layouts`` other starts' layouts (those whose walls leave both
cells free). It reports, in metres, ``layout_shift``: how far the proposed subgoal moves on average when only the
layout changes; ``goal_offset``: how far the proposed subgoal lies from the goal in the start's own layout (for scale);
and ``swaps``: how many layout swaps were measured. A subgoal that does not move with the layout is one offset for every
layout: it cannot lead the lower level round walls it does not see. Whether it moves the right way, in the start's own
layout: ``in_sight`` (the share of subgoals the gripper sees, no wall cell on the straight way to it, so that the lower
level can go straight there), ``path_gain`` (how much nearer the goal along the free cells the subgoal is than the
gripper, :meth:`~sb3_dipper.envs.fetch.MazeGeometry.path_distances`, over the subgoals that have such a way) and
``useful`` (the share both in sight and nearer the goal along the free cells). The case ``policy`` is the model's
higher policy, ``goal`` the goal as the subgoal (the control): the goal is in sight only where no wall stands between.
DIPPER's planner is not used (``predict`` does not plan at the profiles). It writes ``layout_sensitivity.json`` in the
zoo run folder; with ``--csv``, one row per model and case.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import torch as th
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

from sb3_dipper.envs.fetch import MazeGeometry

# Run as a script, this file's folder is on the path; the scripts' folder above it holds the modules it shares.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from configs import measure_runs, measurement_parser, trained_hierarchy

COLUMNS = ("observations", "layout_shift", "goal_offset", "swaps", "in_sight", "path_gain", "useful")
# Points per straight way checked for walls (a cell is 5 cm; the mazes' ways are at most about 60 cm).
SIGHT_SAMPLES = 48
ObsDict = dict[str, np.ndarray]


def grid_index(maze: MazeGeometry, points: np.ndarray) -> np.ndarray:
    """``(N,)``: the flat index in a maze observation's grid of each point's cell."""
    cells = np.array([maze.cell_of(point) for point in np.atleast_2d(points)])
    return cells[:, 0] * maze.cols + cells[:, 1]


def layout_swaps(observations: ObsDict, maze: MazeGeometry, n_layouts: int) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)``: start ``i``'s gripper and goal shown in start ``j``'s layout, for the first ``n_layouts``
    other starts ``j`` whose layout leaves both of start ``i``'s cells free (1 in the grid is a wall)."""
    grids = observations["observation"][:, 3:]
    gripper_cells = grid_index(maze, observations["achieved_goal"])
    goal_cells = grid_index(maze, observations["desired_goal"])
    starts, layouts = [], []
    for i in range(len(grids)):
        free = (grids[:, gripper_cells[i]] == 0) & (grids[:, goal_cells[i]] == 0)
        free[i] = False
        others = np.flatnonzero(free)[:n_layouts]
        starts += [i] * len(others)
        layouts += others.tolist()
    return np.array(starts, dtype=np.int64), np.array(layouts, dtype=np.int64)


def in_layouts(observations: ObsDict, starts: np.ndarray, layouts: np.ndarray) -> ObsDict:
    """The observations of ``starts`` with the grids of ``layouts`` in place of their own."""
    swapped = {key: value[starts].copy() for key, value in observations.items()}
    swapped["observation"][:, 3:] = observations["observation"][layouts, 3:]
    return swapped


def in_sight(observations: ObsDict, targets: np.ndarray, maze: MazeGeometry) -> np.ndarray:
    """``(N,)``: whether the straight way from each gripper to its target crosses only free cells of its layout."""
    grids = observations["observation"][:, 3:]
    start = observations["achieved_goal"][:, None, :2]
    fractions = np.linspace(0.0, 1.0, SIGHT_SAMPLES)[None, :, None]
    points = start + fractions * (targets[:, None, :2] - start)
    cells = grid_index(maze, points.reshape(-1, 2)).reshape(len(targets), SIGHT_SAMPLES)
    return (np.take_along_axis(grids, cells, axis=1) == 0).all(axis=1)


def way_round(observations: ObsDict, targets: np.ndarray, maze: MazeGeometry) -> dict[str, float]:
    """``in_sight``, ``path_gain`` and ``useful`` of the ``targets`` (world subgoals) in the observations' layouts."""
    grips, goals = observations["achieved_goal"], observations["desired_goal"]
    gain = maze.path_distances(observations["observation"], grips, goals) - maze.path_distances(
        observations["observation"], targets, goals
    )
    seen = in_sight(observations, targets, maze)
    # A target in a wall cell with no free neighbour has no way to the goal (an infinite distance): not a gain.
    finite = np.isfinite(gain)
    mean_gain = float(gain[finite].mean()) if finite.any() else float("nan")
    return {"in_sight": float(seen.mean()), "path_gain": mean_gain, "useful": float(np.mean(seen & (gain > 0)))}


def layout_sensitivity(
    observations: ObsDict, subgoals_of: Callable[[ObsDict], np.ndarray], maze: MazeGeometry, n_layouts: int
) -> dict[str, float]:
    """:data:`COLUMNS` but the way round for original ``observations`` and ``subgoals_of(observations) -> (N, d)`` world
    subgoals."""
    own = subgoals_of(observations)
    starts, layouts = layout_swaps(observations, maze, n_layouts)
    goal_dim = own.shape[-1]
    offsets = np.linalg.norm(own - observations["desired_goal"][:, :goal_dim], axis=-1)
    if len(starts) == 0:
        return {"observations": len(own), "layout_shift": float("nan"), "goal_offset": float(offsets.mean()), "swaps": 0}
    moved = subgoals_of(in_layouts(observations, starts, layouts))
    shifts = np.linalg.norm(moved - own[starts], axis=-1)
    return {
        "observations": len(own),
        "layout_shift": float(shifts.mean()),
        "goal_offset": float(offsets.mean()),
        "swaps": len(starts),
    }


def start_observations(env: VecEnv, n_starts: int) -> ObsDict:
    """``n_starts`` episode starts of ``env``, as the env's own (unnormalised) observations."""
    batches: list[ObsDict] = []
    while sum(len(batch["observation"]) for batch in batches) < n_starts:
        env.reset()
        batch = env.get_original_obs() if isinstance(env, VecNormalize) else env.buf_obs  # type: ignore[attr-defined]
        batches.append({key: np.array(value, dtype=np.float32) for key, value in dict(batch).items()})
    return {key: np.concatenate([batch[key] for batch in batches])[:n_starts] for key in batches[0]}


def measure(
    run: Path, algo: str, env_id: str, n_starts: int, model_file: Path | None, n_layouts: int
) -> tuple[int, dict[str, dict[str, float]]]:
    model, env = trained_hierarchy(run, algo, env_id, model_file)
    maze = env.get_attr("maze")[0] if env.has_attr("maze") else None
    if not isinstance(maze, MazeGeometry):
        raise ValueError(f"{run}: {env_id} is not a Fetch maze (its env has no MazeGeometry)")
    assert model.subgoal_space is not None
    space = model.subgoal_space

    def subgoals_of(observations: ObsDict) -> np.ndarray:
        shown = env.normalize_obs(observations) if isinstance(env, VecNormalize) else observations
        return space.to_world(model._high_level_actions(shown, deterministic=True))  # type: ignore[arg-type]

    observations = start_observations(env, n_starts)
    policy = layout_sensitivity(observations, subgoals_of, maze, n_layouts)
    policy.update(way_round(observations, subgoals_of(observations), maze))
    goals = observations["desired_goal"][:, : space.dim]
    control = {"observations": len(goals), "layout_shift": 0.0, "goal_offset": 0.0, "swaps": 0}
    control.update(way_round(observations, goals, maze))
    return model.num_timesteps, {"policy": policy, "goal": control}


def main() -> None:
    parser = measurement_parser(__doc__, episodes=200)
    parser.add_argument("--layouts", type=int, default=10, help="other layouts each start is shown in")
    args = parser.parse_args()
    th.set_num_threads(1)

    def measure_model(run: Path, algo: str, env_id: str, n_starts: int, model_file: Path | None) -> tuple[int, dict]:
        return measure(run, algo, env_id, n_starts, model_file, args.layouts)

    measure_runs(parser, args, measure_model, "layout_sensitivity.json", ("case", *COLUMNS))


if __name__ == "__main__":
    main()
