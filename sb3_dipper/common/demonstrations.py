"""Demonstrations: scripted experts' episodes, stored as npz (read without pickle), or read from a Minari dataset.

The DIPPER paper gives every method one demonstration on pick-and-place, push and kitchen (the authors' PIPER code uses
it only for a Q-filtered behaviour-cloning loss on the lower level). Our scripted experts (``sb3_dipper.envs.EXPERTS``)
make those demonstrations: ``sb3-dipper-demos --env FetchPush-v4 --n-episodes 10 --out push_demos.npz``.

npz schema (one row per step, episodes concatenated in order):

- ``observations/<key>`` ``(N, ...)``: the observation before each step, for ``observation``, ``achieved_goal``,
  ``desired_goal``
- ``next_observations/<key>`` ``(N, ...)``: the observation after it
- ``actions`` ``(N, action_dim)``, ``rewards`` ``(N,)``, ``successes`` ``(N,)`` (``info["is_success"]`` after the step)
- ``episode_lengths`` ``(E,)``: lengths of the episodes, summing to N
- ``env_id`` (a string, as a 0-d array)
- ``sha256`` (optional; a string, as a 0-d array): the :func:`arrays_digest` of the other arrays, which the cache of the
  scripted demonstrations behind ``demo_path="auto"`` records when it is written and checks when it is read

Files are written under a temporary name and renamed into place, and read without pickle; every error names the file.
"""

from __future__ import annotations

import hashlib
import re
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

from sb3_dipper.common.files import read_npz, save_npz
from sb3_dipper.common.validation import as_int

OBSERVATION_KEYS = ("observation", "achieved_goal", "desired_goal")
# The member of an npz file that records the digest of its other arrays.
DIGEST_KEY = "sha256"
# Added to the demonstrations' std: an input the demonstration never varies (a fixed goal, an untouched object) is
# scaled by 100 instead of without bound.
DEMO_STD_FLOOR = 1e-2


class ScriptedExpert(Protocol):
    """A deterministic controller: ``reset()`` at the start of an episode, then one action per observation."""

    def reset(self) -> None: ...

    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray: ...


@dataclass
class Demonstrations:
    """Episodes of a goal env, concatenated step by step (see the module docstring for the arrays)."""

    observations: dict[str, np.ndarray]
    next_observations: dict[str, np.ndarray]
    actions: np.ndarray
    rewards: np.ndarray
    successes: np.ndarray
    episode_lengths: np.ndarray
    env_id: str = ""
    # Where the episodes come from (a file, for messages); not saved.
    source: str = ""

    def __len__(self) -> int:
        return int(self.actions.shape[0])

    @property
    def n_episodes(self) -> int:
        return int(self.episode_lengths.size)

    @property
    def episode_starts(self) -> np.ndarray:
        return np.concatenate([[0], np.cumsum(self.episode_lengths)[:-1]]).astype(np.int64)

    def first_episodes(self, n_episodes: int) -> Demonstrations:
        """The first ``n_episodes`` episodes (the algorithms' ``n_demos``), from 1 to all of them."""
        where = self.source or "the demonstrations"
        if n_episodes < 1:
            raise ValueError(f"n_demos must be at least 1 (demonstration episodes to use from {where}), got {n_episodes}")
        if n_episodes > self.n_episodes:
            raise ValueError(
                f"Asked for {n_episodes} demonstrations but the file holds {self.n_episodes} episodes ({where}): choose "
                f"n_demos between 1 and {self.n_episodes}, or record more (sb3-dipper-demos --n-episodes {n_episodes})"
            )
        steps = int(self.episode_lengths[:n_episodes].sum())
        return Demonstrations(
            observations={key: value[:steps] for key, value in self.observations.items()},
            next_observations={key: value[:steps] for key, value in self.next_observations.items()},
            actions=self.actions[:steps],
            rewards=self.rewards[:steps],
            successes=self.successes[:steps],
            episode_lengths=self.episode_lengths[:n_episodes],
            env_id=self.env_id,
            source=self.source,
        )

    def check_spaces(self, observation_space: spaces.Space, action_space: spaces.Space) -> None:
        """Refuse demonstrations whose observations or actions do not fit the env's spaces (recorded on another env?).

        Unchecked, they would fail at the first update with a tensor-size error that names neither file nor env.
        """
        assert isinstance(observation_space, spaces.Dict), "goal envs have Dict observations"
        where = self.source or "the demonstrations"
        recorded_on = f" (the file says {self.env_id})" if self.env_id else ""
        fix = (
            f"were they recorded on another env{recorded_on}? Pass demonstrations of this env as demo_path "
            "(sb3-dipper-demos --env <env id> --out demos.npz records them)."
        )
        missing = [key for key in observation_space.spaces if key not in self.observations]
        if missing:
            raise ValueError(f"{where} has no {missing} observations, which the env has: {fix}")
        for key, space in observation_space.spaces.items():
            for found in (self.observations[key].shape[1:], self.next_observations[key].shape[1:]):
                if found != space.shape:
                    raise ValueError(
                        f"The demonstrations' {key} has shape {found} but the env's has {space.shape} ({where}): {fix}"
                    )
        if self.actions.shape[1:] != action_space.shape:
            raise ValueError(
                f"The demonstrations' actions have shape {self.actions.shape[1:]} but the env's have "
                f"{action_space.shape} ({where}): {fix}"
            )

    def save(self, path: str | Path, with_digest: bool = False) -> None:
        """Write the episodes to an npz file (schema: see the module docstring), atomically.

        :param path: the file
        :param with_digest: also record the :func:`arrays_digest` of the arrays, which
            ``load_demonstrations(path, verify_digest=True)`` checks
        """
        arrays: dict[str, np.ndarray] = {f"observations/{key}": value for key, value in self.observations.items()}
        arrays.update({f"next_observations/{key}": value for key, value in self.next_observations.items()})
        arrays.update(
            actions=self.actions,
            rewards=self.rewards,
            successes=self.successes,
            episode_lengths=self.episode_lengths,
            env_id=np.array(self.env_id),
        )
        if with_digest:
            arrays[DIGEST_KEY] = np.array(arrays_digest(arrays))
        save_npz(path, arrays)


def arrays_digest(arrays: Mapping[str, np.ndarray]) -> str:
    """The sha256 of named arrays (hex): each array's name, dtype, shape and bytes, in name order."""
    digest = hashlib.sha256()
    for key in sorted(arrays):
        array = np.ascontiguousarray(arrays[key])
        digest.update(f"{key}\0{array.dtype.str}\0{array.shape}\0".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def written_without_digest(path: str | Path) -> bool:
    """Whether ``path`` is a readable npz archive that records no digest (:data:`DIGEST_KEY`).

    ``False`` for a file that is not one (missing, truncated, ...): reading it says what is wrong.
    """
    try:
        with zipfile.ZipFile(path) as archive:
            return f"{DIGEST_KEY}.npy" not in archive.namelist()
    except (OSError, zipfile.BadZipFile):
        return False


def collect_demonstrations(
    env_id: str,
    expert_factory: Callable[[gym.Env], ScriptedExpert],
    n_episodes: int,
    seed: int = 0,
    env_kwargs: dict[str, Any] | None = None,
    only_successes: bool = True,
    action_noise: float = 0.0,
) -> Demonstrations:
    """Run ``expert_factory(env.unwrapped)`` for ``n_episodes`` episodes (seeds ``seed``, ``seed + 1``, ...).

    With ``only_successes``, failed episodes are skipped (the next seed is tried) so every demonstration succeeds.

    With ``action_noise`` the episodes are DART's (Laskey et al., 2017): the env executes the expert's action plus
    Gaussian noise of that standard deviation (clipped to the action box), while the file records the expert's own
    action. A scripted expert reads the simulator, so it corrects the noise's drift, and a clone of the episodes learns
    those corrections: the states a clone's own small errors lead to are in the data. The noise is drawn from a
    generator seeded with ``seed``, so the same arguments give the same episodes.
    """
    if not (np.isfinite(action_noise) and action_noise >= 0.0):
        raise ValueError(f"action_noise must be a finite standard deviation >= 0, got {action_noise}")
    n_episodes = as_int("n_episodes", n_episodes, 1, "a demonstration file holds at least one episode")
    env = gym.make(env_id, **(env_kwargs or {}))
    expert = expert_factory(env.unwrapped)
    noise = np.random.default_rng(seed)
    episodes: list[dict[str, Any]] = []
    episode_seed = seed
    while len(episodes) < n_episodes:
        if episode_seed > seed + 10 * n_episodes + 100:
            raise RuntimeError(
                f"The expert of {env_id} keeps failing: {len(episodes)} successes in {episode_seed - seed} tries"
            )
        episode = _run_episode(env, expert, episode_seed, action_noise, noise)
        episode_seed += 1
        if episode["successes"][-1] or not only_successes:
            episodes.append(episode)
    env.close()
    return Demonstrations(
        observations={key: np.concatenate([e["observations"][key] for e in episodes]) for key in OBSERVATION_KEYS},
        next_observations={key: np.concatenate([e["next_observations"][key] for e in episodes]) for key in OBSERVATION_KEYS},
        actions=np.concatenate([e["actions"] for e in episodes]).astype(np.float32),
        rewards=np.concatenate([e["rewards"] for e in episodes]).astype(np.float32),
        successes=np.concatenate([e["successes"] for e in episodes]).astype(np.float32),
        episode_lengths=np.array([len(e["actions"]) for e in episodes], dtype=np.int64),
        env_id=env_id,
        source=f"the scripted expert of {env_id}" + (f", action noise {action_noise} (DART)" if action_noise else ""),
    )


def _run_episode(
    env: gym.Env, expert: ScriptedExpert, seed: int, action_noise: float, noise: np.random.Generator
) -> dict[str, Any]:
    obs, _ = env.reset(seed=seed)
    expert.reset()
    steps: dict[str, list] = {"observations": [], "next_observations": [], "actions": [], "rewards": [], "successes": []}
    low, high = env.action_space.low, env.action_space.high  # type: ignore[attr-defined]
    done = False
    while not done:
        action = np.asarray(expert.act(obs), dtype=np.float32)
        executed = (
            action if action_noise == 0.0 else np.clip(action + action_noise * noise.standard_normal(action.shape), low, high)
        )
        next_obs, reward, terminated, truncated, info = env.step(executed.astype(np.float32))
        for name, value in (("observations", obs), ("next_observations", next_obs)):
            steps[name].append({key: np.asarray(value[key], dtype=np.float32) for key in OBSERVATION_KEYS})
        steps["actions"].append(action)
        steps["rewards"].append(reward)
        steps["successes"].append(float(info.get("is_success", 0.0)))
        obs, done = next_obs, terminated or truncated
    for name in ("observations", "next_observations"):
        steps[name] = {key: np.stack([step[key] for step in steps[name]]) for key in OBSERVATION_KEYS}  # type: ignore[assignment]
    return steps


# demo_path="auto" (and "auto:dart<N>"): each task's scripted demonstrations, registered by the module that defines the
# task (sb3_dipper.envs registers one maker per scripted expert), so this floor names no task.
_DEFAULT_DEMONSTRATIONS: dict[str, Callable[[int, float], Demonstrations]] = {}
# "auto:dart<N>": N episodes of the expert executed with this action noise, the setting measured on the kitchen
# (research log docs/research/2026-11-30-paper-tasks-cpu.md, 2026-12-03: "The kitchen's lower level is a noisy clone").
DART_ACTION_NOISE = 0.1
_DART_SPEC = re.compile(r"auto:dart([1-9][0-9]*)")


def register_default_demonstrations(env_id: str, make: Callable[[int, float], Demonstrations]) -> None:
    """Declare what ``demo_path="auto"`` loads for ``env_id``: ``make(n_episodes, action_noise)`` returns that many
    episodes of the task's scripted expert, executed with that action noise (DART when above zero)."""
    _DEFAULT_DEMONSTRATIONS[env_id] = make


def demonstrations_for(demo_path: str, env: VecEnv, n_demos: int | None = None) -> Demonstrations:
    """The first ``n_demos`` episodes of the demonstrations ``demo_path`` names for ``env``: an npz file or a Minari
    dataset directory (:func:`load_demonstrations`); ``"auto"``, the single default demonstration registered for the
    env's id (the paper's one demonstration); or ``"auto:dart<N>"``, N DART episodes of the same expert (its actions
    executed with Gaussian noise of standard deviation ``DART_ACTION_NOISE``, beyond the paper; see
    :func:`collect_demonstrations`).

    :param demo_path: the demonstrations
    :param env: the env they are for
    :param n_demos: how many episodes to use, from the first (``None``: all N of ``"auto:dart<N>"``, the one of
        ``"auto"``, the first episode of a file or dataset)
    """
    if demo_path != "auto" and not demo_path.startswith("auto:"):
        return load_demonstrations(demo_path).first_episodes(1 if n_demos is None else n_demos)
    dart = _DART_SPEC.fullmatch(demo_path)
    if demo_path != "auto" and dart is None:
        raise ValueError(
            f"demo_path={demo_path!r}: the scripted expert's demonstrations are 'auto' (one episode) or 'auto:dart<N>' "
            "(N >= 1 DART episodes, e.g. 'auto:dart20'); a file whose name starts with 'auto:' is passed as './' + name"
        )
    spec = env.get_attr("spec", indices=[0])[0]
    if spec is None:
        raise ValueError(f"demo_path={demo_path!r} needs an env made from a registered id; pass a demonstration file instead")
    if spec.id not in _DEFAULT_DEMONSTRATIONS:
        raise ValueError(
            f"demo_path={demo_path!r}: no scripted demonstrations for {spec.id!r} (tasks with them: "
            f"{sorted(_DEFAULT_DEMONSTRATIONS)}); pass a demonstration file (sb3-dipper-demos) instead"
        )
    n_episodes = 1 if dart is None else int(dart.group(1))
    if n_demos is not None and n_demos > n_episodes:
        more = (
            f"demo_path='auto:dart{n_demos}' (that many DART episodes of the same expert)"
            if dart is not None
            else f"demo_path='auto:dart{n_demos}' (DART episodes of the same expert) or a file of {n_demos} episodes "
            f"(sb3-dipper-demos --env {spec.id} --n-episodes {n_demos})"
        )
        raise ValueError(
            f"n_demos={n_demos} asks for more episodes than demo_path={demo_path!r} makes ({n_episodes}): for more, "
            f"use {more}; or use at most n_demos={n_episodes} (leaving n_demos out uses all {n_episodes})"
        )
    demonstrations = _DEFAULT_DEMONSTRATIONS[spec.id](n_episodes, 0.0 if dart is None else DART_ACTION_NOISE)
    return demonstrations.first_episodes(n_episodes if n_demos is None else n_demos)


def normalize_like_demonstrations(
    vec_normalize: VecNormalize, demonstrations: Demonstrations, std_floor: float = DEMO_STD_FLOOR
) -> None:
    """Fix ``vec_normalize``'s observation statistics to the states the demonstrations act in: every normalised key is
    scaled by the demonstrations' mean and ``std + std_floor``, and the statistics stop following the visited states
    (``training = False``, SB3's way to freeze them).

    Running statistics of the visited states scale an object's joint by the std the exploring agent gives it: on the
    kitchen, where exploration hardly moves the microwave door or the burner knob, a demonstration's states are then
    clipped and the lower level cannot see the task's progress (measured in the research log
    docs/research/2026-11-30-paper-tasks-cpu.md, 2026-12-03: "The kitchen scaled like its demonstrations").

    :param vec_normalize: the training env's ``VecNormalize`` (with ``norm_obs=True``)
    :param demonstrations: the episodes whose states define the scale
    :param std_floor: added to each input's std
    """
    for key in vec_normalize.norm_obs_keys or []:
        rms = vec_normalize.obs_rms[key]  # type: ignore[index]
        states = demonstrations.observations[key].reshape(len(demonstrations), -1).astype(np.float64)
        std = states.std(axis=0) + std_floor
        # VecNormalize divides by sqrt(var + epsilon): this var makes that divisor exactly std.
        rms.mean = states.mean(axis=0).reshape(rms.mean.shape)
        rms.var = np.maximum(std**2 - vec_normalize.epsilon, 0.0).reshape(rms.var.shape)
        rms.count = float(len(demonstrations))
    vec_normalize.training = False


def load_demonstrations(path: str | Path, n_episodes: int | None = None, verify_digest: bool = False) -> Demonstrations:
    """Read demonstrations from our npz file or from a Minari dataset directory (needs ``pip install minari``).

    :param path: the npz file or Minari directory
    :param n_episodes: keep the first ``n_episodes`` (from 1 to all; default: all)
    :param verify_digest: refuse an npz file whose arrays do not match the digest it records, or that records none
        (``Demonstrations.save(path, with_digest=True)`` writes one)
    """
    path = Path(path)
    demonstrations = _load_minari(path) if path.is_dir() else _load_npz(path, verify_digest)
    return demonstrations if n_episodes is None else demonstrations.first_episodes(n_episodes)


def _load_npz(path: Path, verify_digest: bool) -> Demonstrations:
    arrays = read_npz(
        path,
        "demonstration file",
        "demo_path takes an npz file written by sb3-dipper-demos (or Demonstrations.save), a Minari dataset directory "
        'or "auto" / "auto:dart<N>".',
    )
    recorded = arrays.pop(DIGEST_KEY, None)
    if verify_digest and (recorded is None or str(recorded) != arrays_digest(arrays)):
        problem = "records no digest" if recorded is None else "does not match the digest recorded when it was written"
        raise ValueError(f"Demonstration file {path}: its content {problem} (was it edited, or damaged?).")
    required = ["actions", "rewards", "successes", "episode_lengths"] + [
        f"{group}/{key}" for group in ("observations", "next_observations") for key in OBSERVATION_KEYS
    ]
    missing = [key for key in required if key not in arrays]
    if missing:
        raise ValueError(f"Malformed demonstration file {path}: missing {missing} (schema: sb3_dipper.common.demonstrations)")
    for key in required:
        if arrays[key].dtype.kind not in "biuf" or arrays[key].ndim == 0:
            raise ValueError(
                f"Malformed demonstration file {path}: {key} must be an array of numbers, got {arrays[key].dtype} "
                f"of shape {arrays[key].shape}"
            )
    n_steps = arrays["actions"].shape[0]
    lengths = arrays["episode_lengths"]
    if lengths.ndim != 1 or lengths.sum() != n_steps or np.any(lengths < 1):
        raise ValueError(f"Malformed demonstration file {path}: episode_lengths must be positive and sum to {n_steps} steps")
    for key in required:
        if arrays[key].shape[0] != n_steps and key != "episode_lengths":
            raise ValueError(f"Malformed demonstration file {path}: {key} has {arrays[key].shape[0]} rows, not {n_steps}")
        if not np.all(np.isfinite(arrays[key])):
            raise ValueError(f"Malformed demonstration file {path}: {key} holds NaN or infinite values")
    return Demonstrations(
        observations={key: arrays[f"observations/{key}"].astype(np.float32) for key in OBSERVATION_KEYS},
        next_observations={key: arrays[f"next_observations/{key}"].astype(np.float32) for key in OBSERVATION_KEYS},
        actions=arrays["actions"].astype(np.float32),
        rewards=arrays["rewards"].astype(np.float32),
        successes=arrays["successes"].astype(np.float32),
        episode_lengths=lengths.astype(np.int64),
        env_id=str(arrays.get("env_id", "")),
        source=str(path),
    )


def _load_minari(path: Path) -> Demonstrations:
    try:
        from minari import MinariDataset  # type: ignore[import-not-found]
    except ImportError as error:
        raise ImportError(f"{path} is a directory: reading a Minari dataset needs `pip install minari`") from error
    dataset = MinariDataset(path / "data" if (path / "data").is_dir() else path)
    episodes = list(dataset.iterate_episodes())
    if not episodes or not isinstance(episodes[0].observations, dict):
        raise ValueError(f"Minari dataset {path} must hold goal-env episodes with Dict observations {OBSERVATION_KEYS}")
    missing = [key for key in OBSERVATION_KEYS if key not in episodes[0].observations]
    if missing:
        raise ValueError(f"Minari dataset {path} has no observation keys {missing}; nested goals must be flattened first")

    def stacked(part: Callable[[Any], dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
        return {key: np.concatenate([part(e)[key] for e in episodes]).astype(np.float32) for key in OBSERVATION_KEYS}

    return Demonstrations(
        observations=stacked(lambda e: {key: e.observations[key][:-1] for key in OBSERVATION_KEYS}),
        next_observations=stacked(lambda e: {key: e.observations[key][1:] for key in OBSERVATION_KEYS}),
        actions=np.concatenate([e.actions for e in episodes]).astype(np.float32),
        rewards=np.concatenate([e.rewards for e in episodes]).astype(np.float32),
        successes=np.concatenate([np.asarray(e.infos.get("is_success", np.zeros(len(e.actions)))) for e in episodes]).astype(
            np.float32
        ),
        episode_lengths=np.array([len(e.actions) for e in episodes], dtype=np.int64),
        env_id=str(dataset.env_spec.id if dataset.env_spec is not None else ""),
        source=str(path),
    )
