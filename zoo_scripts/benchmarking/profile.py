"""``benchmark.py throughput``, ``profiles`` and ``updates``: how fast the algorithms train, measured in one process.

Each measure times chunks of work interleaved in a new random order every round (:func:`interleaved_seconds`), so the
ratios between algorithms share the machine's changing load; the absolute times do not travel.
"""

from __future__ import annotations

import argparse
import ast
import inspect
import json
import os
import random
import statistics
import sys
import time
from collections.abc import Callable, Mapping
from functools import partial
from typing import Any

import numpy as np
import torch as th
from configs import torch_threads
from plot import LABELS, label
from stable_baselines3.common.callbacks import BaseCallback

from sb3_dipper.common.files import write_bytes_atomically
from sb3_dipper.zoo.run_config import ALGORITHMS, ZOO_KEYS, load_entry, make_env, make_model

from .report import REPO, RESULTS_DIR, command_line, write_section

THROUGHPUT_LOWER = dict(batch_size=256, buffer_size=100_000, learning_starts=1000, gamma=0.95, tau=0.005)


class StopAfterSteps(BaseCallback):
    """Ends ``learn`` once it has trained ``steps`` more primitive steps."""

    def __init__(self, steps: int) -> None:
        super().__init__()
        self.steps = steps
        self.start = 0

    def _on_training_start(self) -> None:
        self.start = self.model.num_timesteps

    def _on_step(self) -> bool:
        return self.model.num_timesteps - self.start < self.steps


def train_within_run(model: Any, steps: int) -> None:
    """``steps`` more training steps of ``model`` as a part of its run of ``model.run_budget`` primitive steps (the
    entry's ``n_timesteps``): ``learn`` is told the run's budget and stopped after ``steps``, so whatever follows the
    run's progress is where such a run has it. A ``learn(steps)`` of its own would end its run every chunk: the
    preference methods would label a round's most pairs at every option (their labels are due in step with the run),
    which a run of the entry's budget labels a few at a time."""
    model.learn(model.run_budget - model.num_timesteps, callback=StopAfterSteps(steps), reset_num_timesteps=False)


def run_model(algo: str, env_id: str, overrides: dict[str, Any] | None = None) -> Any:
    """The model of ``algo``'s entry for ``env_id`` (seed 0), with its run's budget as ``run_budget``."""
    model, _, n_timesteps = make_model(algo, env_id, seed=0, overrides=overrides)
    model.run_budget = n_timesteps  # type: ignore[attr-defined]
    return model


def throughput_models(env_id: str, net_arch: list[int]) -> dict[str, Any]:
    """SAC+HER and the hierarchical algorithms with the same lower networks, batch size and updates per step."""
    models = {}
    for algo in ("sac", "hier", "dipper", "dipper_paper"):
        overrides: dict[str, Any] = dict(THROUGHPUT_LOWER, n_envs=1)
        if algo == "sac":
            overrides.update(policy_kwargs=dict(net_arch=net_arch), train_freq=1, gradient_steps=1)
        else:
            overrides.update(low_policy_kwargs=dict(net_arch=net_arch), train_freq=1, gradient_steps=1)
        models[algo] = run_model(algo, env_id, overrides)
    return models


def interleaved_seconds(chunks: Mapping[str, Callable[[], Any]], repeats: int) -> dict[str, list[float]]:
    """Seconds of each of ``repeats`` calls of every chunk of work, the chunks in a new random order every round, so
    that every one meets the machine's changing load alike."""
    seconds: dict[str, list[float]] = {name: [] for name in chunks}
    order = list(chunks)
    for _ in range(repeats):
        random.shuffle(order)
        for name in order:
            start = time.perf_counter()
            chunks[name]()
            seconds[name].append(time.perf_counter() - start)
    return seconds


def time_spent_in(model: Any, method_names: tuple[str, ...]) -> dict[str, float]:
    """Wrap ``model``'s methods so that the seconds spent in each add up in the returned dict (from now on)."""
    seconds = dict.fromkeys(method_names, 0.0)

    def timed(name: str, method: Callable[..., Any]) -> Callable[..., Any]:
        def call(*args: Any, **kwargs: Any) -> Any:
            start = time.perf_counter()
            try:
                return method(*args, **kwargs)
            finally:
                seconds[name] += time.perf_counter() - start

        return call

    for name in method_names:
        setattr(model, name, timed(name, getattr(model, name)))
    return seconds


def higher_level_seconds(models: dict[str, Any]) -> dict[str, dict[str, float]]:
    """For each two-level model (one with a lower-level update, ``_train_low_level``), the seconds its ``train`` and
    that update take from now on: the difference is the higher level's part of training (labels and its updates)."""
    return {
        name: time_spent_in(model, ("train", "_train_low_level"))
        for name, model in models.items()
        if hasattr(model, "_train_low_level")
    }


def training_chunks(models: dict[str, Any], steps: int) -> dict[str, Callable[[], Any]]:
    """``steps`` more training steps of each model within its run (:func:`train_within_run`), as chunks for
    :func:`interleaved_seconds`."""
    return {name: partial(train_within_run, model, steps) for name, model in models.items()}


def run_throughput(args: argparse.Namespace) -> None:
    th.set_num_threads(torch_threads())
    models = throughput_models(args.env, args.net_arch)
    for model in models.values():
        train_within_run(model, THROUGHPUT_LOWER["learning_starts"] + args.steps)
    seconds = interleaved_seconds(training_chunks(models, args.steps), args.repeats)
    seconds = {algo: [chunk / args.steps for chunk in chunks] for algo, chunks in seconds.items()}
    per_step = {algo: statistics.median(values) for algo, values in seconds.items()}
    rows = [f"| {LABELS[algo]} | {per_step[algo] * 1e3:.2f} | {per_step[algo] / per_step['sac']:.2f} |" for algo in models]
    body = (
        f"Seconds per primitive step on `{args.env}`, one env, lower networks {args.net_arch}, batch 256, one lower "
        f"gradient step per primitive step for every algorithm (SAC+HER: its only level). Median of {args.repeats} "
        f"interleaved chunks of {args.steps} steps after warm-up, measured in one process.\n\n"
        "| algorithm | ms per step | ratio to SAC+HER |\n|---|---|---|\n" + "\n".join(rows)
    )
    if args.write:
        record = {"seconds_per_step": seconds, "median": per_step}
        write_bytes_atomically(RESULTS_DIR / "throughput.json", json.dumps(record, indent=1).encode())
        write_section("throughput", body, command_line("benchmark.py", sys.argv[1:]))
    print(body)


def env_steps_per_second(env_id: str, n_envs: int, steps: int) -> float:
    """Primitive steps per second of the task's vectorised env under uniformly random actions (the limit if updates
    and acting were free)."""
    env = make_env(env_id, {"n_envs": n_envs}, seed=0)
    env.reset()
    start = time.perf_counter()
    for _ in range(steps // n_envs):
        env.step(np.stack([env.action_space.sample() for _ in range(n_envs)]))
    seconds = time.perf_counter() - start
    env.close()
    return (steps // n_envs) * n_envs / seconds


FUSED_ADAM = "fused"  # the variant name of a profile whose optimizers are fused Adam


def fused_adam_overrides(algo: str, env_id: str) -> dict[str, Any]:
    """The entry's network kwargs of every level with ``optimizer_kwargs={"fused": True}``: ``torch.optim.Adam``'s
    one-kernel update of all parameters instead of its loop over tensors in Python, the same math (the SAC entropy
    coefficient's own optimizer, used only with ``ent_coef='auto'``, stays SB3's)."""
    entry = load_entry(algo, env_id)
    levels = ["policy_kwargs"]
    if "low_policy_kwargs" in inspect.signature(ALGORITHMS[algo]).parameters:
        levels.append("low_policy_kwargs")
    overrides = {}
    for key in levels:
        kwargs = dict(entry.get(key) or {})
        kwargs["optimizer_kwargs"] = {**kwargs.get("optimizer_kwargs", {}), "fused": True}
        overrides[key] = kwargs
    return overrides


def profile_variants(variants: list[list[str]]) -> dict[str, dict[str, Any]]:
    """``--variant NAME KEY=VALUE ...`` of ``profiles`` as ``{NAME: {KEY: value}}``, the values Python literals.

    :param variants: one list per ``--variant``: its name, then its assignments
    """
    parsed: dict[str, dict[str, Any]] = {}
    for name, *assignments in variants:
        if "=" in name or not assignments:
            raise ValueError(f"--variant takes a name, then key=value (e.g. --variant b128 batch_size=128), got {name!r}")
        overrides = {}
        for assignment in assignments:
            key, separator, value = assignment.partition("=")
            if not separator or not key:
                raise ValueError(f"--variant {name} takes key=value after its name, got {assignment!r}")
            try:
                overrides[key] = ast.literal_eval(value)
            except (ValueError, SyntaxError):
                raise ValueError(
                    f"--variant {name} {assignment}: {value!r} is not a Python literal "
                    "(a number, string in quotes, list or dict: policy_kwargs=\"{'net_arch': [64, 64]}\")"
                ) from None
        parsed[name] = overrides
    return parsed


def variant_overrides(algo: str, env_id: str, changes: dict[str, Any]) -> dict[str, Any] | None:
    """One ``--variant``'s ``changes`` as overrides of an algorithm's entry, or None where the algorithm lacks a keyword.

    A dict value updates the entry's dict (``policy_kwargs={'optimizer_kwargs': {'fused': True}}`` keeps the entry's
    ``net_arch``), so a variant changes only what it names; a variant of a lower level's keywords
    (``low_policy_kwargs``, ``bc_coef``) is skipped for SAC+HER, which has none.
    """
    # Deprecated keywords too (bc_coef: demo_kwargs["bc_coef"]), which the constructors still take.
    keywords = set(inspect.signature(ALGORITHMS[algo]).parameters) | set(ZOO_KEYS)
    keywords |= set(getattr(ALGORITHMS[algo], "deprecated_parameters", {}))
    if not set(changes) <= keywords:
        return None
    entry = load_entry(algo, env_id)
    return {
        key: {**entry[key], **value} if isinstance(value, dict) and isinstance(entry.get(key), dict) else value
        for key, value in changes.items()
    }


def run_profiles(args: argparse.Namespace) -> None:
    """Training steps per second of each algorithm at each task's CPU profile, beside the env's own step rate.

    The models of one task are warmed up past ``learning_starts``, then trained in interleaved chunks of
    ``--steps`` primitive steps (the median chunk counts), in this one process, so the ratios share the machine's state.
    With ``--fused-adam`` each algorithm is measured a second time, as ``<algo>-fused``, with fused Adam optimizers;
    each ``--variant NAME KEY=VALUE ...`` measures it once more, as ``<algo>-NAME``, with those hyperparameters changed
    (:func:`variant_overrides`).
    """
    th.set_num_threads(torch_threads())
    variants = profile_variants(args.variant)
    rows, records = [], []
    for env_id in args.envs:
        models = {algo: run_model(algo, env_id) for algo in args.algos}
        if args.fused_adam:
            for algo in args.algos:
                overrides = fused_adam_overrides(algo, env_id)
                models[f"{algo}-{FUSED_ADAM}"] = run_model(algo, env_id, overrides)
        for name, changes in variants.items():
            for algo in args.algos:
                variant = variant_overrides(algo, env_id, changes)
                if variant is not None:
                    models[f"{algo}-{name}"] = run_model(algo, env_id, variant)
            if not any(f"{algo}-{name}" in models for algo in args.algos):
                raise ValueError(f"--variant {name}: none of {', '.join(args.algos)} takes {', '.join(sorted(changes))}")
        n_envs = models[args.algos[0]].n_envs
        env_rate = env_steps_per_second(env_id, n_envs, args.steps)
        for model in models.values():
            train_within_run(model, int(getattr(model, "learning_starts", 0)) + args.steps)
        spent = higher_level_seconds(models)
        seconds = interleaved_seconds(training_chunks(models, args.steps), args.repeats)
        rates = {algo: args.steps / statistics.median(values) for algo, values in seconds.items()}
        baseline = rates.get("sac")
        for algo, rate in rates.items():
            versus_sac = f"{rate / baseline:.2f}" if baseline else "-"
            higher = spent.get(algo)
            share = (higher["train"] - higher["_train_low_level"]) / sum(seconds[algo]) if higher else None
            cells = f"{rate / env_rate:.2f} | {versus_sac} | {'-' if share is None else f'{share:.0%}'}"
            rows.append(f"| `{env_id}` | {label(algo)} | {rate:.0f} | {env_rate:.0f} | {cells} |")
            share_cell = "" if share is None else f"{share:.3f}"
            records.append(f"{env_id},{algo},{models[algo].n_envs},{rate:.2f},{env_rate:.2f},{share_cell}")
        print(rows[-len(rates) :], flush=True)
    csv = RESULTS_DIR / f"{args.name}.csv"
    body = (
        "Primitive steps per second while training, at each task's CPU profile (`hyperparams/<algo>.yml`), one torch "
        f"thread, median of {args.repeats} interleaved chunks of {args.steps:,} steps after `learning_starts`, measured "
        "in one process; the env rate is the same vectorised env under random actions (the limit if updates were "
        "free). The higher level's share is the part of the measured time a two-level algorithm spends training outside "
        f"its lower level's updates (labelling pairs and the higher-level updates). CSV: `{os.path.relpath(csv, REPO)}`.\n\n"
        "| task | algorithm | training steps/s | env steps/s | ratio to env | ratio to SAC+HER | higher level's share |\n"
        "|---|---|---|---|---|---|---|\n" + "\n".join(rows)
    )
    if args.write:
        header = "env,algo,n_envs,train_steps_per_second,env_steps_per_second,higher_level_share"
        write_bytes_atomically(csv, "\n".join([header, *records, ""]).encode())
        write_section(args.name, body, command_line("benchmark.py", sys.argv[1:]))
    print(body)


def update_steps(model: Any) -> dict[str, Any]:
    """One update of each kind on a trained DIPPER: SB3's own ``SAC.train`` on the lower SAC (same networks, buffer and
    batch), the lower level's DemoSAC step (behaviour cloning, clipped targets) and DIPPER's higher-level update."""
    from stable_baselines3 import SAC

    lower, batch_size = model.lower, model.batch_size
    return {
        "SB3 SAC.train, 1 gradient step": lambda: SAC.train(lower, 1, batch_size),
        "DemoSAC.train, 1 gradient step": lambda: lower.train(1, batch_size),
        "DIPPER higher-level update": model._train_high_level,
    }


def repeat_call(function: Callable[[], Any], times: int) -> None:
    for _ in range(times):
        function()


def run_updates(args: argparse.Namespace) -> None:
    """Milliseconds per training update at a task's DIPPER CPU profile, and their ratios to SB3's SAC update.

    The model trains ``learning_starts + --warmup`` primitive steps first (filled buffers, labelled pairs); then each
    kind of update runs ``--updates`` times per round, the kinds in a new random order every round, all in this one
    process, so the ratios share the machine's state (the absolute times do not travel).
    """
    th.set_num_threads(torch_threads())
    model = run_model("dipper", args.env)
    train_within_run(model, int(getattr(model, "learning_starts", 0)) + args.warmup)
    chunks = {name: partial(repeat_call, update, args.updates) for name, update in update_steps(model).items()}
    seconds = interleaved_seconds(chunks, args.repeats)
    per_update = {name: statistics.median(values) / args.updates for name, values in seconds.items()}
    baseline = per_update["SB3 SAC.train, 1 gradient step"]
    rows = [f"| {name} | {value * 1e3:.2f} | {value / baseline:.2f} |" for name, value in per_update.items()]
    print(
        f"Milliseconds per update at `{args.env}`'s DIPPER CPU profile (`hyperparams/dipper.yml`), one torch thread, "
        f"median of {args.repeats} interleaved rounds of {args.updates} updates after {args.warmup:,} training steps "
        "past `learning_starts`, measured in one process.\n\n"
        "| update | ms per update | ratio to SB3 SAC |\n|---|---|---|\n" + "\n".join(rows)
    )
