"""`make demo`: train DIPPER on PointMazeFourRooms-v0, print its evaluation success rate, plot its success curve.

The hyperparameters are the zoo entry ``hyperparams/dipper.yml: PointMazeFourRooms-v0``. During training an
``EvalCallback`` measures the deterministic success rate every ``--eval-freq`` steps (``evaluations.npz``); at the end the
model is evaluated on ``--final-episodes`` fresh episodes, saved, and the curve is written to ``success_curve.png``.
The entry plans subgoals over achieved states, so the final evaluation says who acted: the model as trained (with the
share of subgoals its planner proposed) and its preference-trained policy alone, with the planner off.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

# configs lives beside this script: importable when the script is imported too (its tests), not only when run.
sys.path.insert(0, str(Path(__file__).resolve().parent))
import matplotlib
import torch as th

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from configs import evaluate, load_entry, make_env, make_model, torch_threads

from sb3_dipper.common.files import read_npz, write_atomically
from sb3_dipper.zoo.callbacks import AtomicEvalCallback

ENV_ID = "PointMazeFourRooms-v0"


def final_success(model, env_id: str, seed: int, n_episodes: int, planner: bool) -> dict[str, float]:
    """Deterministic success over ``n_episodes`` new episodes (at the goal when the episode ends) and the share of
    subgoals the planner proposed; ``planner=False`` evaluates the preference-trained policy alone."""
    eval_env = make_env(env_id, load_entry("dipper", env_id), seed=seed, n_envs=10)
    in_predict = model.planner.in_predict
    model.planner.in_predict = planner and model.planner.mode == "subgoal"
    try:
        return evaluate(model, eval_env, n_episodes)
    finally:
        model.planner.in_predict = in_predict


def plot_success_curve(evaluations: Path, output: Path) -> None:
    """The success curve of the evaluations recorded in ``evaluations`` (``evaluations.npz``), as a png at ``output``."""
    fix = "It is written by this demo's evaluations: run the demo again to write it anew."
    data = read_npz(evaluations, "evaluation record", fix)
    steps, success = data["timesteps"], data["successes"].mean(axis=1)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(steps, success, marker="o", label="DIPPER")
    ax.set(xlabel="primitive steps", ylabel="success rate (deterministic)", ylim=(-0.02, 1.02), title=ENV_ID)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    fig.tight_layout()
    write_atomically(output, lambda handle: fig.savefig(handle, format="png", dpi=120))
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--output-dir", default="demo_output", type=Path)
    parser.add_argument("--seed", default=0, type=int)
    parser.add_argument("--n-timesteps", default=None, type=int, help="override the YAML's n_timesteps")
    parser.add_argument("--eval-freq", default=20_000, type=int, help="primitive steps between evaluations")
    parser.add_argument("--eval-episodes", default=20, type=int)
    parser.add_argument("--final-episodes", default=100, type=int)
    args = parser.parse_args()
    th.set_num_threads(torch_threads())
    args.output_dir.mkdir(parents=True, exist_ok=True)

    model, env, n_timesteps = make_model("dipper", ENV_ID, seed=args.seed, verbose=0)
    n_timesteps = args.n_timesteps or n_timesteps
    eval_callback = AtomicEvalCallback(
        make_env(ENV_ID, load_entry("dipper", ENV_ID), seed=args.seed + 1000, n_envs=10),
        eval_freq=max(args.eval_freq // env.num_envs, 1),
        n_eval_episodes=args.eval_episodes,
        log_path=str(args.output_dir),
        deterministic=True,
        verbose=0,
    )
    print(f"Training DIPPER on {ENV_ID} for {n_timesteps} primitive steps ({env.num_envs} envs, seed {args.seed})")
    start = time.time()
    model.learn(n_timesteps, callback=eval_callback, progress_bar=True)
    training_minutes = (time.time() - start) / 60
    model.save(args.output_dir / "dipper_point_maze")

    as_trained = final_success(model, ENV_ID, args.seed + 2000, args.final_episodes, planner=True)
    policy_alone = final_success(model, ENV_ID, args.seed + 2000, args.final_episodes, planner=False)
    plot_success_curve(args.output_dir / "evaluations.npz", args.output_dir / "success_curve.png")
    print(f"Training took {training_minutes:.1f} minutes")
    print(
        f"Deterministic success over {args.final_episodes} episodes: {as_trained['success']:.2f} as trained (the planner "
        f"proposed {as_trained['planned_share']:.0%} of the subgoals, the preference-trained policy the rest); "
        f"{policy_alone['success']:.2f} with the policy alone (planner off)"
    )
    print(f"Success curve: {args.output_dir / 'success_curve.png'}; model: {args.output_dir / 'dipper_point_maze.zip'}")


if __name__ == "__main__":
    main()
