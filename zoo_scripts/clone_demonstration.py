"""What can the task's one demonstration teach on its own? Pure behaviour cloning, run closed loop.

    python zoo_scripts/clone_demonstration.py FetchPickAndPlaceFixed-v0 FetchPushFixed-v0 --csv clone.csv

A deterministic MLP (``--net-arch``, [256, 256] by default: the lower level's size in the CPU profiles) is fitted to
the default demonstration's actions from its observation and desired goal (mean squared error, Adam, inputs
standardised on the demonstration), then acts alone in the env for ``--episodes`` seeded episodes. No reinforcement
learning is involved: where the clone solves a task, the single demonstration holds everything the lower level needs,
and the behaviour-cloning term can hand it over; where the clone fails, the lower level has to learn the missing part
by trial and error. Per episode the script reports the success and the first step at which the state leaves the
demonstration's (largest difference of the ``observation`` vectors above ``--tolerance``): the moment compounding
errors take the clone off the demonstrated path. Episode seed 0 starts where the demonstration started.

``--demo-path`` clones the first ``--n-demos`` episodes of a demonstration file instead (``sb3-dipper-demos``; with
``--action-noise`` it writes DART episodes, whose states include the expert's corrections of its own drift):

    sb3-dipper-demos --env FrankaKitchenMicrowaveBurner-v0 --n-episodes 20 --action-noise 0.1 --out kitchen-dart.npz
    python zoo_scripts/clone_demonstration.py FrankaKitchenMicrowaveBurner-v0 --demo-path kitchen-dart.npz --n-demos 1 5 20

The departure step is then measured from the file's first episode.
"""

from __future__ import annotations

import argparse
import csv
import io
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.torch_layers import create_mlp

import sb3_dipper  # noqa: F401  (registers our env ids)
from sb3_dipper.common.demonstrations import Demonstrations
from sb3_dipper.common.files import write_bytes_atomically
from sb3_dipper.common.demonstrations import load_demonstrations
from sb3_dipper.envs.demos import default_demonstrations

CSV_FIELDS = (
    "env",
    "demonstrations",
    "n_demos",
    "fit_steps",
    "fit_loss",
    "episode_seed",
    "success",
    "departure_step",
    "episode_steps",
)


@dataclass
class Clone:
    """A deterministic policy ``tanh(mlp((observation, desired_goal) standardised))`` fitted to a demonstration."""

    network: th.nn.Sequential
    mean: np.ndarray
    std: np.ndarray
    fit_loss: float

    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        features = (np.concatenate([observation["observation"], observation["desired_goal"]], -1) - self.mean) / self.std
        with th.no_grad():
            return self.network(th.as_tensor(features, dtype=th.float32)).numpy()


def fit_clone(demonstrations: Demonstrations, net_arch: list[int], steps: int, batch_size: int = 128, seed: int = 0) -> Clone:
    """Fit a :class:`Clone` to every step of ``demonstrations`` by ``steps`` Adam steps (learning rate 1e-3) on the
    mean squared action error. Actions are assumed in ``[-1, 1]`` (the tanh output), as in every task here."""
    generator = np.random.default_rng(seed)
    th.manual_seed(seed)
    inputs = np.concatenate([demonstrations.observations["observation"], demonstrations.observations["desired_goal"]], 1)
    # The floor keeps inputs that never vary in the demonstration (a fixed goal) from being scaled up without bound.
    mean, std = inputs.mean(0), inputs.std(0) + 1e-2
    features = th.as_tensor((inputs - mean) / std, dtype=th.float32)
    targets = th.as_tensor(demonstrations.actions, dtype=th.float32)
    network = th.nn.Sequential(*create_mlp(features.shape[1], targets.shape[1], net_arch, squash_output=True))
    optimizer = th.optim.Adam(network.parameters(), lr=1e-3)
    loss = th.zeros(())
    for _ in range(steps):
        rows = th.as_tensor(generator.integers(0, len(targets), batch_size))
        loss = (network(features[rows]) - targets[rows]).pow(2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return Clone(network, mean, std, loss.item())


def first_departure(states: np.ndarray, demonstrated: np.ndarray, tolerance: float) -> int | None:
    """The first step ``t`` at which ``max |states[t] - demonstrated[t]|`` exceeds ``tolerance`` (over the steps both
    have), or ``None`` if the states never leave the demonstrated ones."""
    n_steps = min(len(states), len(demonstrated))
    far = np.abs(states[:n_steps] - demonstrated[:n_steps]).max(axis=1) > tolerance
    return int(np.argmax(far)) if far.any() else None


def run_clone(clone: Clone, env: gym.Env, demonstration: Demonstrations, episode_seed: int, tolerance: float) -> dict:
    """One closed-loop episode of the clone from ``env.reset(seed=episode_seed)``: its success (``is_success`` at the
    last step, as the benchmarks evaluate), departure step from the demonstration's states and length."""
    observation, _ = env.reset(seed=episode_seed)
    states = []
    done, info = False, dict[str, Any]()
    while not done:
        observation, _, terminated, truncated, info = env.step(clone.act(observation))
        states.append(observation["observation"])
        done = terminated or truncated
    departure = first_departure(np.array(states), demonstration.next_observations["observation"], tolerance)
    return {
        "success": float(info.get("is_success", 0.0)),
        "departure_step": "" if departure is None else departure,
        "episode_steps": len(states),
    }


def clone_rows(
    env_id: str,
    net_arch: list[int],
    fit_steps: int,
    episodes: int,
    tolerance: float,
    demo_path: Path | None = None,
    n_demos: int = 1,
) -> list[dict]:
    """Fit a clone of the first ``n_demos`` episodes of ``demo_path`` (default: ``env_id``'s default demonstration)
    and run it for episode seeds ``0 .. episodes - 1``."""
    demonstrations = default_demonstrations(env_id) if demo_path is None else load_demonstrations(demo_path)
    demonstrations = demonstrations.first_episodes(n_demos)
    env = gym.make(env_id)
    try:
        demonstrations.check_spaces(env.observation_space, env.action_space)
        clone = fit_clone(demonstrations, net_arch, fit_steps)
        return [
            {
                "env": env_id,
                "demonstrations": "default" if demo_path is None else demo_path.name,
                "n_demos": n_demos,
                "fit_steps": fit_steps,
                "fit_loss": f"{clone.fit_loss:.2e}",
                "episode_seed": seed,
                **run_clone(clone, env, demonstrations.first_episodes(1), seed, tolerance),
            }
            for seed in range(episodes)
        ]
    finally:
        env.close()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("envs", nargs="+", help="tasks with a default demonstration (a registered scripted expert)")
    parser.add_argument("--net-arch", type=int, nargs="+", default=[256, 256])
    parser.add_argument("--fit-steps", type=int, default=5000)
    parser.add_argument("--episodes", type=int, default=8)
    parser.add_argument("--tolerance", type=float, default=0.05, help="largest observation difference still on the path")
    parser.add_argument("--demo-path", type=Path, help="an npz file of sb3-dipper-demos (default: the task's default one)")
    parser.add_argument(
        "--n-demos", type=int, nargs="+", default=[1], help="clone the file's first N episodes (one clone per N)"
    )
    parser.add_argument("--csv", type=Path, help="also write one row per episode here")
    args = parser.parse_args(argv)
    if args.fit_steps < 1 or args.episodes < 1 or min(args.n_demos) < 1:
        parser.error("--fit-steps, --episodes and --n-demos must be at least 1")
    if args.demo_path is not None and len(args.envs) != 1:
        parser.error(f"--demo-path holds one task's demonstrations: give one env, not {len(args.envs)}")
    th.set_num_threads(1)
    rows = []
    for env_id in args.envs:
        for n_demos in args.n_demos:
            env_rows = clone_rows(
                env_id, args.net_arch, args.fit_steps, args.episodes, args.tolerance, args.demo_path, n_demos
            )
            departures = [row["departure_step"] for row in env_rows]
            cloned = "" if args.demo_path is None else f" ({n_demos} of {args.demo_path.name})"
            print(
                f"{env_id}{cloned}: success {np.mean([row['success'] for row in env_rows]):.2f} over {args.episodes} "
                f"episodes, fit loss {env_rows[0]['fit_loss']}, departure steps {departures} of "
                f"{env_rows[0]['episode_steps']}"
            )
            rows += env_rows
    if args.csv is not None:
        text = io.StringIO()
        writer = csv.DictWriter(text, fieldnames=CSV_FIELDS)
        writer.writeheader()
        writer.writerows(rows)
        write_bytes_atomically(args.csv, text.getvalue().encode())


if __name__ == "__main__":
    main()
