"""Which level fails? A trained hierarchical model driven by the demonstration's subgoals, beside its own higher level.

    python zoo_scripts/oracle_subgoals.py logs/dipper/FetchPickAndPlaceFixed-v0_1 --algo dipper

On a fixed task (the env starts where the single default demonstration started), the demonstration's achieved
subgoals at option boundaries (steps K, 2K, ..., the last step) are a sequence of subgoals the expert reached. Driving
the trained lower level with them measures the lower level alone: if it reaches them, the lower level has learnt what
the demonstration shows, and a failure of the full policy lies with the higher level's proposals. The script prints,
for the oracle subgoals and for the model's own higher level (both deterministic), the episode success and the share of
options that ended within the subgoal threshold, and writes them as ``oracle_subgoals.json`` in the zoo run folder.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

from sb3_dipper.common.files import write_bytes_atomically
from sb3_dipper.common.hierarchical import HierarchicalAlgorithm
from sb3_dipper.envs.demos import default_demonstrations

sys.path.insert(0, str(Path(__file__).resolve().parent))
from configs import trained_run


def oracle_subgoals(env_id: str, option_steps: int, model: HierarchicalAlgorithm) -> np.ndarray:
    """The default demonstration's achieved subgoals after steps K, 2K, ... and after its last step, in world units."""
    assert model.subgoal_space is not None
    demonstration = default_demonstrations(env_id).first_episodes(1)
    achieved = model.subgoal_space.project(demonstration.next_observations["achieved_goal"])
    ends = list(range(option_steps - 1, len(achieved), option_steps))
    if ends[-1] != len(achieved) - 1:
        ends.append(len(achieved) - 1)
    return achieved[ends].astype(np.float32)


def run_episodes(model: HierarchicalAlgorithm, env: VecEnv, n_episodes: int, subgoals: np.ndarray | None) -> dict[str, float]:
    """Deterministic episodes; ``subgoals`` (one row per option) replaces the higher level when given."""
    assert model.subgoal_space is not None
    space, option_steps = model.subgoal_space, model.option_steps
    successes: list[float] = []
    reached: list[float] = []
    while len(successes) < n_episodes:
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
                    current = np.repeat(subgoals[min(step // option_steps, len(subgoals) - 1)][None], n_envs, axis=0)
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a zoo run folder (logs/<algo>/<env>_<n>) holding <env>.zip")
    parser.add_argument("--algo", required=True, help="zoo name of the model's algorithm (dipper, hier, ...)")
    parser.add_argument("--env", help="task (default: the run folder's name without its _<n>)")
    parser.add_argument("--episodes", type=int, default=20)
    args = parser.parse_args()
    env_id = args.env or args.run.name.rsplit("_", 1)[0]
    model, env = trained_run(args.run, args.algo, env_id, seed=20_000)
    assert isinstance(model, HierarchicalAlgorithm)
    results = {
        "oracle": run_episodes(model, env, args.episodes, oracle_subgoals(env_id, model.option_steps, model)),
        "higher_level": run_episodes(model, env, args.episodes, None),
    }
    write_bytes_atomically(args.run / "oracle_subgoals.json", json.dumps(results, indent=1).encode())
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
