"""Scripted-expert demonstrations of our tasks: the single default demonstration and the ``sb3-dipper-demos`` command."""

from __future__ import annotations

import argparse
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from sb3_dipper.common.demonstrations import (
    Demonstrations,
    collect_demonstrations,
    load_demonstrations,
    written_without_digest,
)
from sb3_dipper.common.files import npz_path


def expert_demonstrations(
    env_id: str,
    n_episodes: int,
    seed: int = 0,
    env_kwargs: dict[str, Any] | None = None,
    only_successes: bool = True,
    action_noise: float = 0.0,
) -> Demonstrations:
    """Episodes of the registered scripted expert of ``env_id`` (``action_noise``: DART episodes, see
    :func:`~sb3_dipper.common.demonstrations.collect_demonstrations`)."""
    from sb3_dipper.envs import EXPERTS

    if env_id not in EXPERTS:
        raise ValueError(f"No scripted expert for {env_id!r}; experts exist for {sorted(EXPERTS)}")
    return collect_demonstrations(env_id, EXPERTS[env_id], n_episodes, seed, env_kwargs, only_successes, action_noise)


def default_demonstration_path(env_id: str, n_episodes: int = 1, action_noise: float = 0.0) -> Path:
    """Where the scripted demonstrations of ``env_id`` behind ``demo_path="auto"`` (one episode, no noise) and
    ``"auto:dart<N>"`` are cached (``$SB3_DIPPER_CACHE`` or ~/.cache/sb3-dipper)."""
    cache = Path(os.environ.get("SB3_DIPPER_CACHE", Path.home() / ".cache" / "sb3-dipper"))
    recipe = "" if (n_episodes, action_noise) == (1, 0.0) else f"-{n_episodes}-noise{action_noise:g}"
    return cache / "demonstrations" / f"{env_id}{recipe}.npz"


def default_demonstrations(env_id: str, n_episodes: int = 1, action_noise: float = 0.0) -> Demonstrations:
    """The task's scripted demonstrations: the expert's first ``n_episodes`` successful episodes from seed 0, executed
    with ``action_noise`` (DART when above zero), made on first use. By default the single default demonstration.

    The expert, the seeded env and the seeded noise are deterministic, so a cached file and a fresh one hold the same
    episodes (those of ``sb3-dipper-demos --env ENV --n-episodes N --action-noise SIGMA``). The file is written under a
    temporary name and renamed into place (``Demonstrations.save``), so a process that finds it (parallel tests, zoo
    workers) never reads half of it. It records the sha256 of its arrays, checked whenever it is read: a cache changed
    since (its actions scaled, a hand edit, a damaged disk) is refused, naming the file to delete. A cache written
    before the digest was recorded is made again, with a warning.
    """
    path = default_demonstration_path(env_id, n_episodes, action_noise)
    uncheckable = written_without_digest(path)
    if uncheckable:
        warnings.warn(
            f"{path} was cached before sb3-dipper recorded a digest of its content, so it cannot be checked: it is made "
            "again from the scripted expert (the same episodes, made in the same way)."
        )
    if uncheckable or not path.exists():
        demonstrations = expert_demonstrations(env_id, n_episodes=n_episodes, seed=0, action_noise=action_noise)
        demonstrations.save(path, with_digest=True)
    try:
        return load_demonstrations(path, verify_digest=True)
    except ValueError as error:
        raise ValueError(
            f"{error} This file is a cached scripted demonstration of {env_id}: delete {path} and it is made again "
            "on next use."
        ) from error


def main(argv: list[str] | None = None) -> None:
    """``sb3-dipper-demos``: write N scripted-expert demonstrations of an env to an npz file."""
    parser = argparse.ArgumentParser(description="Write scripted-expert demonstrations to an npz file.")
    parser.add_argument("--env", required=True, help="env id with a registered scripted expert")
    parser.add_argument("--n-episodes", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--keep-failures", action="store_true", help="also keep episodes the expert failed")
    parser.add_argument(
        "--action-noise",
        type=float,
        default=0.0,
        help="DART: execute the expert's action plus Gaussian noise of this standard deviation, record the expert's",
    )
    args = parser.parse_args(argv)
    if args.n_episodes < 1:
        parser.error(f"--n-episodes must be at least 1 (the episodes to write), got {args.n_episodes}")
    if not args.action_noise >= 0.0:
        parser.error(f"--action-noise must be >= 0, got {args.action_noise}")
    import sb3_dipper  # noqa: F401  (registers our env ids)

    demonstrations = expert_demonstrations(
        args.env, args.n_episodes, args.seed, only_successes=not args.keep_failures, action_noise=args.action_noise
    )
    demonstrations.save(args.out)
    success = demonstrations.successes[np.cumsum(demonstrations.episode_lengths) - 1].mean()
    steps = len(demonstrations)
    # save appends .npz to a name without it, as numpy does: name the file written.
    print(f"Wrote {demonstrations.n_episodes} episodes ({steps} steps, final success {success:.2f}) to {npz_path(args.out)}")


if __name__ == "__main__":
    main()
