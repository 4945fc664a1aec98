"""What can the task's one demonstration teach on its own? Pure behaviour cloning, run closed loop.

    python zoo_scripts/research/clone_demonstration.py FetchPickAndPlaceFixed-v0 FetchPushFixed-v0 --csv clone.csv

A deterministic MLP (``--net-arch``, [256, 256] by default: the lower level's size in the CPU profiles) is fitted to
the default demonstration's actions from its observation and desired goal (mean squared error, Adam, inputs
standardised on the demonstration), then acts alone in the env for ``--episodes`` seeded episodes. No reinforcement
learning is involved: where the clone solves a task, the single demonstration holds everything the lower level needs,
and the behaviour-cloning term can hand it over; where the clone fails, the lower level has to learn the missing part
by trial and error. Per episode the script reports the success and the first step at which the state leaves the
demonstration's (largest difference of the ``observation`` vectors above ``--tolerance``): the moment compounding
errors take the clone off the demonstrated path. Episode seed 0 starts where the demonstration started.

The demonstrations are the expert's episodes from seed 0 on (``sb3-dipper-demos``), so on a task with random starts
and goals the episodes ``0 .. --episodes - 1`` replay the demonstrated ones: they measure whether the clone reproduces
its demonstrations. ``--first-episode-seed 20000`` runs episodes no demonstration saw, the seeds
``planner_share.py`` evaluates a trained run on, which is what a trained lower level's success compares with:

    python zoo_scripts/research/clone_demonstration.py FetchPush-v4 --demo-path push-dart20.npz --n-demos 20 --option-steps 7 \
        --drive goal --episodes 20 --first-episode-seed 20000

``--demo-path`` clones the first ``--n-demos`` episodes of a demonstration file instead (``sb3-dipper-demos``; with
``--action-noise`` it writes DART episodes, whose states include the expert's corrections of its own drift):

    sb3-dipper-demos --env FrankaKitchenMicrowaveBurner-v0 --n-episodes 20 --action-noise 0.1 --out kitchen-dart.npz
    python zoo_scripts/research/clone_demonstration.py FrankaKitchenMicrowaveBurner-v0 --demo-path kitchen-dart.npz \
        --n-demos 1 5 20

The departure step is then measured from the file's first episode. A clone's success can hang on its initialisation
and batch order (the kitchen's; research log docs/research/2026-11-30-paper-tasks-cpu.md, 2026-12-03: "The kitchen's
demonstration made DART"): ``--fit-seeds 0 1 2`` fits one clone per seed.

``--option-steps K`` clones as a lower level learns from the demonstrations: each step under a subgoal the algorithms'
own :class:`~sb3_dipper.common.imitation.DemonstrationBuffer` samples (a later achieved subgoal of its episode, or the
goal), then drives the clone with the default demonstration's subgoals every K steps, as ``oracle_subgoals.py`` drives
a trained run's lower level; the CSV then also gives the share of options that ended at their subgoal. Where this
clone follows the subgoals and a trained lower level does not, the cloning term is not what fails it:

    python zoo_scripts/research/clone_demonstration.py FrankaKitchenMicrowaveBurner-v0 --demo-path kitchen-dart.npz \
        --n-demos 20 --option-steps 15

``--drive goal`` drives that clone with the task's goal as every subgoal instead, as a lower level acts under a higher
level that proposes nothing useful (``planner_share.py``'s ``goal_as_subgoal``): the gap to the demonstration's
subgoals is what a higher level's subgoals could add. ``--batch-size`` sets the demonstration steps per Adam step (128);
a lower level's cloning term sees ``demo_share x batch_size`` of them (32 at the CPU profiles), and on the kitchen a
clone fitted on batches of 32 succeeds far less reliably (the same log, 2026-12-03: "The kitchen's lower level is a
noisy clone").
"""

from __future__ import annotations

import argparse
import csv
import io
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.torch_layers import create_mlp
from stable_baselines3.common.vec_env import DummyVecEnv

import sb3_dipper  # noqa: F401  (registers our env ids)
from sb3_dipper.common.demonstrations import Demonstrations, load_demonstrations
from sb3_dipper.common.files import write_bytes_atomically
from sb3_dipper.common.imitation import DemonstrationBuffer
from sb3_dipper.common.subgoals import SubgoalSpace, resolve_subgoal_space
from sb3_dipper.envs.demos import default_demonstrations

# Run as a script, this file's folder is on the path; the scripts' folder above it holds the modules it shares.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from research.oracle_subgoals import option_subgoal, oracle_subgoals

CSV_FIELDS = (
    "env",
    "demonstrations",
    "n_demos",
    "option_steps",
    "driver",
    "fit_steps",
    "batch_size",
    "fit_seed",
    "fit_loss",
    "episode_seed",
    "success",
    "departure_step",
    "episode_steps",
    "options_reached",
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


def fit_clone(
    sample_batch: Callable[[int], tuple[np.ndarray, np.ndarray]],
    reference_inputs: np.ndarray,
    n_actions: int,
    net_arch: list[int],
    steps: int,
    batch_size: int = 128,
    seed: int = 0,
) -> Clone:
    """Fit a :class:`Clone` by ``steps`` Adam steps (learning rate 1e-3) on the mean squared action error of batches
    ``(inputs, actions) = sample_batch(batch_size)``, inputs standardised by ``reference_inputs``, ``n_actions`` outputs.
    Actions are assumed in ``[-1, 1]`` (the tanh output), as in every task here."""
    th.manual_seed(seed)
    # The floor keeps inputs that never vary in the demonstration (a fixed goal) from being scaled up without bound.
    mean, std = reference_inputs.mean(0), reference_inputs.std(0) + 1e-2
    network = th.nn.Sequential(*create_mlp(reference_inputs.shape[1], n_actions, net_arch, squash_output=True))
    optimizer = th.optim.Adam(network.parameters(), lr=1e-3)
    loss = th.zeros(())
    for _ in range(steps):
        inputs, targets = sample_batch(batch_size)
        features = th.as_tensor((inputs - mean) / std, dtype=th.float32)
        loss = (network(features) - th.as_tensor(targets, dtype=th.float32)).pow(2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return Clone(network, mean, std, loss.item())


def goal_conditioned_inputs(demonstrations: Demonstrations) -> np.ndarray:
    """Every demonstration step's observation and its own desired goal, side by side."""
    return np.concatenate([demonstrations.observations["observation"], demonstrations.observations["desired_goal"]], 1)


def goal_conditioned_batches(
    inputs: np.ndarray, actions: np.ndarray, seed: int
) -> Callable[[int], tuple[np.ndarray, np.ndarray]]:
    """Rows of ``inputs`` (:func:`goal_conditioned_inputs`) and their ``actions``: what a flat goal-conditioned policy
    clones."""
    generator = np.random.default_rng(seed)

    def sample_batch(batch_size: int) -> tuple[np.ndarray, np.ndarray]:
        rows = generator.integers(0, len(inputs), batch_size)
        return inputs[rows], actions[rows]

    return sample_batch


def subgoal_conditioned_batches(buffer: DemonstrationBuffer, seed: int) -> Callable[[int], tuple[np.ndarray, np.ndarray]]:
    """Demonstration steps with the subgoals the lower level clones them under: a later achieved subgoal of the episode
    (probability 0.8) or the projected desired goal, sampled by the algorithms' own :class:`DemonstrationBuffer`."""
    np.random.seed(seed)  # the buffer samples with numpy's global generator, as in training

    def sample_batch(batch_size: int) -> tuple[np.ndarray, np.ndarray]:
        observations, actions, _, _ = buffer.sample(batch_size)
        return np.concatenate([observations["observation"], observations["desired_goal"]], 1), actions

    return sample_batch


def first_departure(states: np.ndarray, demonstrated: np.ndarray, tolerance: float) -> int | None:
    """The first step ``t`` at which ``max |states[t] - demonstrated[t]|`` exceeds ``tolerance`` (over the steps both
    have), or ``None`` if the states never leave the demonstrated ones."""
    n_steps = min(len(states), len(demonstrated))
    far = np.abs(states[:n_steps] - demonstrated[:n_steps]).max(axis=1) > tolerance
    return int(np.argmax(far)) if far.any() else None


def subgoal_space_of(env: gym.Env) -> SubgoalSpace:
    """The subgoal space the algorithms would train ``env`` with (gymnasium-robotics' own ids declare none)."""
    return resolve_subgoal_space(DummyVecEnv([lambda: env]))


def run_clone(
    clone: Clone,
    env: gym.Env,
    demonstration: Demonstrations,
    episode_seed: int,
    tolerance: float,
    subgoals: np.ndarray | None = None,
    option_steps: int = 1,
    goal_as_subgoal: bool = False,
    space: SubgoalSpace | None = None,
) -> dict:
    """One closed-loop episode of the clone from ``env.reset(seed=episode_seed)``: its success (``is_success`` at the
    last step, as the benchmarks evaluate), departure step from the demonstration's states and length. With
    ``subgoals`` (one per option of ``option_steps`` steps) the clone sees the option's subgoal in place of the
    desired goal, as a lower level does, and the share of options that ended within the subgoal threshold is
    reported too; with ``goal_as_subgoal`` every option's subgoal is the episode's desired goal, projected.

    :param space: the subgoal space the clone was fitted with (:func:`subgoal_space_of`), needed when it is driven
    """
    driven = subgoals is not None or goal_as_subgoal
    if driven and space is None:
        raise ValueError("run_clone: a clone driven by subgoals needs their space (space=subgoal_space_of(env))")
    observation, _ = env.reset(seed=episode_seed)
    if space is not None and goal_as_subgoal:  # the episode's goal is fixed at its reset: one subgoal for every option
        subgoals = space.project(observation["desired_goal"])[None]
    states, reached = [], []
    done, info, step = False, dict[str, Any](), 0
    while not done:
        subgoal = None if subgoals is None else option_subgoal(subgoals, step, option_steps)
        seen = observation if subgoal is None else {**observation, "desired_goal": subgoal}
        observation, _, terminated, truncated, info = env.step(clone.act(seen))
        states.append(observation["observation"])
        done = terminated or truncated
        step += 1
        if space is not None and subgoal is not None and (step % option_steps == 0 or done):
            reached.append(float(space.distance(space.project(observation["achieved_goal"]), subgoal) <= space.threshold))
    departure = first_departure(np.array(states), demonstration.next_observations["observation"], tolerance)
    return {
        "success": float(info.get("is_success", 0.0)),
        "departure_step": "" if departure is None else departure,
        "episode_steps": len(states),
        "options_reached": f"{np.mean(reached):.4f}" if reached else "",
    }


def clone_rows(
    env_id: str,
    net_arch: list[int],
    fit_steps: int,
    episodes: int,
    tolerance: float,
    demo_path: Path | None = None,
    n_demos: int = 1,
    option_steps: int | None = None,
    fit_seed: int = 0,
    driver: str = "demonstration",
    batch_size: int = 128,
    first_episode_seed: int = 0,
) -> list[dict]:
    """Fit a clone of the first ``n_demos`` episodes of ``demo_path`` (default: ``env_id``'s default demonstration)
    and run it for episode seeds ``first_episode_seed .. first_episode_seed + episodes - 1``; with ``option_steps``,
    clone and drive it as a lower level (subgoal-conditioned, driven every ``option_steps`` steps by the default
    demonstration's subgoals, or with ``driver="goal"`` by the goal). ``fit_seed`` seeds the network's initialisation
    and the batches of ``batch_size`` demonstration steps."""
    demonstrations = default_demonstrations(env_id) if demo_path is None else load_demonstrations(demo_path)
    demonstrations = demonstrations.first_episodes(n_demos)
    env = gym.make(env_id)
    try:
        demonstrations.check_spaces(env.observation_space, env.action_space)
        subgoals, space = None, None
        if option_steps is None:
            reference_inputs = goal_conditioned_inputs(demonstrations)
            sample_batch = goal_conditioned_batches(reference_inputs, demonstrations.actions, seed=fit_seed)
        else:
            space = subgoal_space_of(env)
            buffer = DemonstrationBuffer(demonstrations, space, demonstrations.actions)
            sample_batch = subgoal_conditioned_batches(buffer, seed=fit_seed)
            subgoals = oracle_subgoals(env_id, option_steps, space) if driver == "demonstration" else None
            reference_inputs, _ = sample_batch(10_000)  # the relabelled subgoals' spread, not the stored goals'
        n_actions = demonstrations.actions.shape[1]
        clone = fit_clone(sample_batch, reference_inputs, n_actions, net_arch, fit_steps, batch_size=batch_size, seed=fit_seed)
        return [
            {
                "env": env_id,
                "demonstrations": "default" if demo_path is None else demo_path.name,
                "n_demos": n_demos,
                "option_steps": "" if option_steps is None else option_steps,
                "driver": "" if option_steps is None else driver,
                "fit_steps": fit_steps,
                "batch_size": batch_size,
                "fit_seed": fit_seed,
                "fit_loss": f"{clone.fit_loss:.2e}",
                "episode_seed": seed,
                **run_clone(
                    clone,
                    env,
                    demonstrations.first_episodes(1),
                    seed,
                    tolerance,
                    subgoals,
                    option_steps or 1,
                    goal_as_subgoal=option_steps is not None and driver == "goal",
                    space=space,
                ),
            }
            for seed in range(first_episode_seed, first_episode_seed + episodes)
        ]
    finally:
        env.close()


def summary(env_id: str, env_rows: list[dict], args: argparse.Namespace) -> str:
    """One console line for the episodes of one clone."""
    cloned = "" if args.demo_path is None else f" ({env_rows[0]['n_demos']} of {args.demo_path.name})"
    reached = ""
    if args.option_steps is not None:
        reached = (
            f", options reached {np.mean([float(row['options_reached']) for row in env_rows]):.2f} "
            f"(driven by the {args.drive}'s subgoals)"
        )
    return (
        f"{env_id}{cloned}, fit seed {env_rows[0]['fit_seed']}: success "
        f"{np.mean([row['success'] for row in env_rows]):.2f}{reached} over {args.episodes} episodes, fit loss "
        f"{env_rows[0]['fit_loss']}, departure steps {[row['departure_step'] for row in env_rows]} of "
        f"{env_rows[0]['episode_steps']}"
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("envs", nargs="+", help="tasks with a default demonstration (a registered scripted expert)")
    parser.add_argument("--net-arch", type=int, nargs="+", default=[256, 256])
    parser.add_argument("--fit-steps", type=int, default=5000)
    parser.add_argument(
        "--batch-size",
        type=int,
        default=128,
        help="demonstration steps per Adam step (a lower level's cloning term sees demo_share x batch_size of them)",
    )
    parser.add_argument("--episodes", type=int, default=8)
    parser.add_argument(
        "--first-episode-seed",
        type=int,
        default=0,
        help="the first episode's seed (the demonstrations are the episodes from seed 0 on: 20000 runs unseen ones)",
    )
    parser.add_argument("--tolerance", type=float, default=0.05, help="largest observation difference still on the path")
    parser.add_argument("--demo-path", type=Path, help="an npz file of sb3-dipper-demos (default: the task's default one)")
    parser.add_argument(
        "--n-demos", type=int, nargs="+", default=[1], help="clone the file's first N episodes (one clone per N)"
    )
    parser.add_argument(
        "--option-steps",
        type=int,
        help="clone as the lower level does (subgoals relabelled from later in each episode) and drive the clone with "
        "the default demonstration's subgoals every K steps, as oracle_subgoals.py drives a trained lower level",
    )
    parser.add_argument(
        "--drive",
        choices=("demonstration", "goal"),
        default="demonstration",
        help="with --option-steps: the subgoals the clone is driven by, the default demonstration's or the goal",
    )
    parser.add_argument(
        "--fit-seeds", type=int, nargs="+", default=[0], help="one clone per seed (initialisation and batches)"
    )
    parser.add_argument("--csv", type=Path, help="also write one row per episode here")
    args = parser.parse_args(argv)
    option_steps = 1 if args.option_steps is None else args.option_steps
    if args.first_episode_seed < 0:
        parser.error("--first-episode-seed must be at least 0 (a seed of env.reset)")
    if min(args.fit_steps, args.batch_size, args.episodes, *args.n_demos, option_steps) < 1:
        parser.error("--fit-steps, --batch-size, --episodes, --n-demos and --option-steps must be at least 1")
    if args.drive != "demonstration" and args.option_steps is None:
        parser.error("--drive goal drives a clone trained as a lower level: give --option-steps too")
    if args.demo_path is not None and len(args.envs) != 1:
        parser.error(f"--demo-path holds one task's demonstrations: give one env, not {len(args.envs)}")
    th.set_num_threads(1)
    rows = []
    for env_id in args.envs:
        for n_demos in args.n_demos:
            for fit_seed in args.fit_seeds:
                env_rows = clone_rows(
                    env_id,
                    args.net_arch,
                    args.fit_steps,
                    args.episodes,
                    args.tolerance,
                    args.demo_path,
                    n_demos,
                    args.option_steps,
                    fit_seed,
                    args.drive,
                    args.batch_size,
                    args.first_episode_seed,
                )
                print(summary(env_id, env_rows, args))
                rows += env_rows
    if args.csv is not None:
        text = io.StringIO()
        writer = csv.DictWriter(text, fieldnames=CSV_FIELDS)
        writer.writeheader()
        writer.writerows(rows)
        write_bytes_atomically(args.csv, text.getvalue().encode())


if __name__ == "__main__":
    main()
