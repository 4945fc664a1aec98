"""The tasks themselves: env steps per second alone and under DIPPER training, scripted-expert success, a rendered frame.

    MUJOCO_GL=egl python zoo_scripts/research/benchmark_envs.py                       # every task, 100 expert episodes each
    MUJOCO_GL=egl python zoo_scripts/research/benchmark_envs.py --envs FetchPush-v4 --expert-episodes 20

Writes (or appends) the ``envs`` section of BENCHMARKS.md (with command, machine and date) and one frame per task to
``docs/tasks/<env>.png`` for the README's task table.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

# Run as a script, this file's folder is on the path; the scripts' folder above it holds the modules it shares.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarking.report import REPO, command_line, write_section
from configs import make_model

import sb3_dipper  # noqa: F401  (registers our env ids)
from sb3_dipper.envs.demos import expert_demonstrations

TASKS = [
    "PointMazeFourRooms-v0",
    "FetchFourRoomMaze-v0",
    "FetchPush-v4",
    "FetchPickAndPlace-v4",
    "FetchPushFixed-v0",
    "FetchPickAndPlaceFixed-v0",
    "FrankaKitchenMicrowaveBurner-v0",
]
FRAMES_DIR = REPO / "docs" / "tasks"
# DIPPER with the CPU profile's networks (lower [64, 64], higher [256, 256], batch 256): the paper's 3x512 / 1024 update
# costs about 0.2 s, which would measure the networks rather than the env.
WARMUP_STEPS = 200
CPU_PROFILE = dict(
    n_envs=1,
    learning_starts=WARMUP_STEPS,
    buffer_size=20_000,
    batch_size=256,
    low_policy_kwargs=dict(net_arch=[64, 64]),
    policy_kwargs=dict(net_arch=[256, 256]),
    demo_kwargs={},  # no demonstrations: the env steps are measured, not the cloning
)


def env_steps_per_second(env_id: str, n_steps: int) -> float:
    """Random-action steps per second of the bare env (resets included)."""
    env = gym.make(env_id)
    env.reset(seed=0)
    env.action_space.seed(0)
    start = time.perf_counter()
    for _ in range(n_steps):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            env.reset()
    elapsed = time.perf_counter() - start
    env.close()
    return n_steps / elapsed


class WarmupClock(BaseCallback):
    """Wall time from the end of the warm-up (both levels learning) to the end of training."""

    def __init__(self, warmup_steps: int) -> None:
        super().__init__()
        self.warmup_steps = warmup_steps
        self.start: float | None = None

    def _on_step(self) -> bool:
        if self.start is None and self.num_timesteps >= self.warmup_steps:
            self.start = time.perf_counter()
        return True


def training_steps_per_second(env_id: str, n_steps: int) -> float:
    """Primitive steps per second of DIPPER training after its warm-up, inside one ``learn`` call.

    One call, so the label schedule is the one of a real run (a second ``learn`` would start with the whole label
    budget due at once).
    """
    model, env, _ = make_model("dipper", env_id, seed=0, overrides=CPU_PROFILE)
    clock = WarmupClock(WARMUP_STEPS + 100)
    model.learn(WARMUP_STEPS + 100 + n_steps, callback=clock)
    assert clock.start is not None
    elapsed = time.perf_counter() - clock.start
    env.close()
    return (model.num_timesteps - clock.warmup_steps) / elapsed


def expert_success(env_id: str, n_episodes: int) -> float:
    """Success of the scripted expert over ``n_episodes`` seeded episodes (failures kept)."""
    demonstrations = expert_demonstrations(env_id, n_episodes, seed=0, only_successes=False)
    return float(demonstrations.successes[np.cumsum(demonstrations.episode_lengths) - 1].mean())


def save_frame(env_id: str) -> Path:
    import matplotlib.pyplot as plt

    env = gym.make(env_id, render_mode="rgb_array")
    env.reset(seed=0)
    frame = np.asarray(env.render())
    env.close()
    FRAMES_DIR.mkdir(parents=True, exist_ok=True)
    path = FRAMES_DIR / f"{env_id}.png"
    plt.imsave(path, frame)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=TASKS)
    parser.add_argument("--env-steps", type=int, default=2000)
    parser.add_argument("--training-steps", type=int, default=1000)
    parser.add_argument("--expert-episodes", type=int, default=100)
    parser.add_argument("--no-frames", action="store_true")
    args = parser.parse_args()
    th.set_num_threads(1)

    rows = []
    for env_id in args.envs:
        alone = env_steps_per_second(env_id, args.env_steps)
        training = training_steps_per_second(env_id, args.training_steps)
        success = expert_success(env_id, args.expert_episodes)
        frame = "" if args.no_frames else f"`{save_frame(env_id).relative_to(REPO)}`"
        rows.append(f"| `{env_id}` | {alone:,.0f} | {training:,.0f} | {success:.2f} | {frame} |")
        print(rows[-1], flush=True)
    body = (
        f"Random-action env steps per second (one env, resets included); primitive steps per second of DIPPER training "
        f"on one env with the CPU profile's networks (lower [64, 64], higher [256, 256], batch 256, one update per step) "
        f"after its warm-up; success of the scripted expert over {args.expert_episodes} seeded episodes (seeds 0 to "
        f"{args.expert_episodes - 1}, failures counted). One torch thread.\n\n"
        "| task | env steps/s | DIPPER training steps/s | expert success | frame |\n|---|---|---|---|---|\n" + "\n".join(rows)
    )
    write_section("envs", body, command_line("research/benchmark_envs.py", sys.argv[1:]))
    print(body)


if __name__ == "__main__":
    main()
