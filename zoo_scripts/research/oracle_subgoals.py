"""Which level fails? A trained hierarchical model driven by the demonstration's subgoals, beside its own higher level.

    python zoo_scripts/research/oracle_subgoals.py logs/dipper/FetchPickAndPlaceFixed-v0_1 --algo dipper
    python zoo_scripts/research/oracle_subgoals.py runs/p9/default/seed_0/dipper/FetchFourRoomMazeFixed-v0_1 --algo dipper \
        --checkpoints --csv curve.csv

Every episode starts where the task's single default demonstration started (the env reset with the demonstration's
seed, 0; on the fixed tasks every seed starts there), so the demonstration's achieved subgoals at option boundaries
(steps K, 2K, ..., the last step) are a sequence of subgoals the expert reached from that start, on the random tasks
too. Driving the trained lower level with them measures the lower level alone: if it reaches them, the lower level has
learnt what the demonstration shows, and a failure of the full policy lies with the higher level's proposals. The
script prints, for the oracle subgoals and for the model's own higher level (both deterministic), the episode success
and the share of options that ended within the subgoal threshold, and writes them as ``oracle_subgoals.json`` in the
zoo run folder. Policy and env are deterministic from one start, so one episode (the default) says it all. With
``--checkpoints`` it also measures every checkpoint the run kept (``rl_model_<steps>_steps.zip``), to follow when the
lower level learns and loses the demonstrated behaviour; ``--csv`` writes one row per model and driver.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

from sb3_dipper.common.hierarchical import HierarchicalAlgorithm
from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.envs.demos import default_demonstrations

# Run as a script, this file's folder is on the path; the scripts' folder above it holds the modules it shares.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from configs import measure_runs, measurement_parser, trained_run

# ``default_demonstrations`` records the expert from ``reset(seed=0)``.
DEMONSTRATION_SEED = 0


def oracle_subgoals(env_id: str, option_steps: int, subgoal_space: SubgoalSpace) -> np.ndarray:
    """The default demonstration's achieved subgoals after steps K, 2K, ... and after its last step, in world units."""
    demonstration = default_demonstrations(env_id).first_episodes(1)
    achieved = subgoal_space.project(demonstration.next_observations["achieved_goal"])
    ends = list(range(option_steps - 1, len(achieved), option_steps))
    if ends[-1] != len(achieved) - 1:
        ends.append(len(achieved) - 1)
    return achieved[ends].astype(np.float32)


def option_subgoal(subgoals: np.ndarray, step: int, option_steps: int) -> np.ndarray:
    """The subgoal of the option running at primitive ``step``: one row per option, the last kept to the end."""
    return subgoals[min(step // option_steps, len(subgoals) - 1)]


def run_episodes(model: HierarchicalAlgorithm, env: VecEnv, n_episodes: int, subgoals: np.ndarray | None) -> dict[str, float]:
    """Deterministic episodes from the demonstration's start; ``subgoals`` (one row per option) replaces the higher
    level when given."""
    assert model.subgoal_space is not None
    space, option_steps = model.subgoal_space, model.option_steps
    successes: list[float] = []
    reached: list[float] = []
    while len(successes) < n_episodes:
        env.seed(DEMONSTRATION_SEED)
        obs = env.reset()
        raw = env.get_original_obs() if isinstance(env, VecNormalize) else obs
        n_envs = env.num_envs
        state: tuple[np.ndarray, np.ndarray] | None = None
        done = np.zeros(n_envs, dtype=bool)
        step = 0
        current = np.zeros((n_envs, space.dim), dtype=np.float32)
        while not done.all():
            if step % option_steps == 0:
                if subgoals is not None:
                    current = np.repeat(option_subgoal(subgoals, step, option_steps)[None], n_envs, axis=0)
                    state = (current.copy(), np.full(n_envs, option_steps, dtype=np.int64))
            actions, new_state = model.predict(obs, state=state, deterministic=True)  # type: ignore[arg-type]
            state = new_state  # type: ignore[assignment]
            if subgoals is None and step % option_steps == 0:
                current = np.array(new_state[0], dtype=np.float32)  # type: ignore[index]
            obs, _, dones, infos = env.step(actions)
            raw = env.get_original_obs() if isinstance(env, VecNormalize) else obs
            step += 1
            for index, info in enumerate(infos):
                if done[index]:
                    continue
                final = info["terminal_observation"] if dones[index] else {key: value[index] for key, value in raw.items()}  # type: ignore[union-attr]
                if isinstance(env, VecNormalize) and dones[index]:
                    final = env.unnormalize_obs(final)  # type: ignore[assignment]
                if step % option_steps == 0 or dones[index]:
                    distance = space.distance(space.project(np.asarray(final["achieved_goal"])), current[index])
                    reached.append(float(distance <= space.threshold))
                if dones[index]:
                    successes.append(float(info.get("is_success", 0.0)))
            done |= dones
    return {"success": float(np.mean(successes[:n_episodes])), "options_reached": float(np.mean(reached))}


def measure(
    run: Path, algo: str, env_id: str, n_episodes: int, model_file: Path | None
) -> tuple[int, dict[str, dict[str, float]]]:
    """Both drivers on the run's model (or on ``model_file``), and the primitive steps that model had trained."""
    model, env = trained_run(run, algo, env_id, seed=DEMONSTRATION_SEED, model_file=model_file)
    if not isinstance(model, HierarchicalAlgorithm):
        raise ValueError(f"{run}: the model is a {type(model).__name__}, not a hierarchical algorithm; it has no subgoals")
    assert model.subgoal_space is not None
    results = {
        "oracle": run_episodes(model, env, n_episodes, oracle_subgoals(env_id, model.option_steps, model.subgoal_space)),
        "higher_level": run_episodes(model, env, n_episodes, None),
    }
    env.close()
    return model.num_timesteps, results


def main() -> None:
    parser = measurement_parser(__doc__, episodes=1, algo=None, algo_help="dipper, hier, ...")
    args = parser.parse_args()
    measure_runs(parser, args, measure, "oracle_subgoals.json", ("driver", "success", "options_reached"))


if __name__ == "__main__":
    main()
