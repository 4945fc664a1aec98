"""Input checks that turn common mistakes into errors naming the problem and the fix."""

from __future__ import annotations

import difflib
import inspect
import math
import os
from collections.abc import Callable, Collection, Iterable, Mapping
from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3 import HerReplayBuffer
from stable_baselines3.common.base_class import maybe_make_env
from stable_baselines3.common.vec_env import VecEnv

from sb3_dipper.common.deprecation import MovedParameter, replacement_text

GOAL_KEYS = ("observation", "achieved_goal", "desired_goal")


class InvalidSetting(ValueError):
    """A setting refused by the checks of :meth:`~sb3_dipper.common.loading.CheckedLoading._check_settings`.

    A ``ValueError``, as before; it also carries the parameter's name, so that ``load`` can say whether the value came
    from the file or from its own keywords.

    :param setting: the parameter's name
    :param message: what is wrong and what is allowed
    """

    def __init__(self, setting: str, message: str) -> None:
        super().__init__(message)
        self.setting = setting


def check_goal_observation_space(observation_space: spaces.Space, algorithm: str) -> None:
    """Refuse envs that are not flat goal envs before SB3 wraps them (its own errors are less helpful)."""
    if not isinstance(observation_space, spaces.Dict) or not set(GOAL_KEYS) <= set(observation_space.spaces):
        raise ValueError(
            f"{algorithm} needs a goal-conditioned env: observations must be a Dict with keys {GOAL_KEYS} "
            f"(gymnasium-robotics style, with a vectorised compute_reward), but got {observation_space}. "
            "Use a goal env such as PointMazeFourRooms-v0 or FetchPush-v4, or wrap yours to expose these keys."
        )
    for key, space in observation_space.spaces.items():
        if isinstance(space, spaces.Dict):
            raise ValueError(
                f"{algorithm} needs flat Box observations, but key {key!r} is a nested Dict ({space}). "
                "Flatten the goals into Boxes (FrankaKitchen-v1 needs this: use FrankaKitchenMicrowaveBurner-v0)."
            )
        if not isinstance(space, spaces.Box) or len(space.shape) != 1:
            raise ValueError(f"{algorithm} needs 1-D Box spaces for every observation key, but {key!r} is {space}.")
    achieved_shape = observation_space["achieved_goal"].shape
    desired_shape = observation_space["desired_goal"].shape
    if achieved_shape != desired_shape:
        # compute_reward, HER relabelling and subgoals all put an achieved goal where a desired one goes.
        raise ValueError(
            f"{algorithm} needs achieved_goal and desired_goal of the same shape, but achieved_goal is {achieved_shape} "
            f"and desired_goal is {desired_shape}. Make both the same quantity (for example the object position), "
            "so that an achieved goal can stand in for a desired one."
        )


def check_finite(
    observation: dict[str, np.ndarray], env_indices: np.ndarray | None = None, source: str = "Observation"
) -> None:
    """Refuse NaN or infinite observations with an error that names the key and the envs.

    :param observation: one row per env
    :param env_indices: the env index of each row (default: row ``i`` is env ``i``)
    :param source: what the observations are, for the message
    """
    for key, value in observation.items():
        if not np.all(np.isfinite(value)):
            bad_rows = np.flatnonzero(~np.all(np.isfinite(value.reshape(value.shape[0], -1)), axis=1))
            bad_envs = bad_rows if env_indices is None else np.asarray(env_indices)[bad_rows]
            raise ValueError(
                f"{source} key {key!r} holds NaN or infinite values (env indices {bad_envs.tolist()}). "
                "Fix the environment, or wrap it in stable_baselines3.common.vec_env.VecCheckNan to find the source."
            )


def checked_goal_observation(observation: Any, observation_space: spaces.Dict) -> tuple[dict[str, np.ndarray], bool]:
    """An observation given to ``predict`` as one row per env, and whether it came batched; refused, naming the key,
    unless it has exactly the goal env's keys, each of the space's shape (one env) or of ``(n_envs, *shape)`` with the
    same ``n_envs``, all finite.

    :param observation: what ``predict`` got
    :param observation_space: the model's (the env's) Dict observation space
    """
    if not isinstance(observation, dict):
        raise TypeError(f"predict acts on a goal env's Dict observations, got {type(observation).__name__}")
    expected = list(observation_space.spaces)
    if set(observation) != set(expected):
        missing = [key for key in expected if key not in observation]
        unknown = [key for key in observation if key not in observation_space.spaces]
        raise ValueError(
            f"predict: the observation's keys must be the env's {expected}"
            + (f"; it lacks {missing}" if missing else "")
            + (f"; it has keys the env does not: {unknown}" if unknown else "")
        )
    batch: dict[str, np.ndarray] = {}
    batch_sizes: dict[str, int | None] = {}
    for key, space in observation_space.spaces.items():
        value, shape = np.asarray(observation[key]), tuple(space.shape or ())
        if not np.issubdtype(value.dtype, np.number):
            raise TypeError(f"predict: observation[{key!r}] must be numbers, got an array of {value.dtype}")
        if value.shape == shape:
            batch_sizes[key] = None
        elif value.shape[1:] == shape and value.ndim == len(shape) + 1:
            batch_sizes[key] = value.shape[0]
        else:
            raise ValueError(
                f"predict: observation[{key!r}] has shape {value.shape}, the env's is {shape}: pass {shape} for one env "
                f"or (n_envs, {', '.join(map(str, shape))}) for several"
            )
        batch[key] = value.reshape(-1, *shape)
    if len(set(batch_sizes.values())) > 1:
        sizes = ", ".join(f"{key}: {'one env' if size is None else f'{size} envs'}" for key, size in batch_sizes.items())
        raise ValueError(f"predict: the observation's keys are for different numbers of envs ({sizes})")
    check_finite(batch, source="predict's observation")
    return batch, next(iter(batch_sizes.values())) is not None


class CheckedPredict:
    """Mixin for an SB3 algorithm of goal envs whose ``predict`` is SB3's: the observation is checked first
    (:func:`checked_goal_observation`), so that a wrong key, shape or a NaN is named instead of failing inside torch."""

    observation_space: spaces.Space

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        checked_goal_observation(observation, self.observation_space)  # type: ignore[arg-type]
        return super().predict(observation, state, episode_start, deterministic)  # type: ignore[misc]


def constructor_parameters(algorithm: type) -> dict[str, inspect.Parameter]:
    """The parameters of ``algorithm(...)``: those of its ``__init__`` after ``self``."""
    parameters = list(inspect.signature(algorithm.__init__).parameters.values())  # type: ignore[misc]
    return {parameter.name: parameter for parameter in parameters[1:]}


def check_keyword_arguments(algorithm: type, kwargs: Mapping[str, Any], source: str = "") -> None:
    """Refuse a keyword argument that ``algorithm``'s constructor does not take, suggesting the closest parameter.

    Hyperparameters reach the constructors as keywords from code, the zoo's YAML files and ``-params``, and Optuna; a
    misspelt one (``option_step``) would be Python's bare ``TypeError``. This is the same ``TypeError``, naming the
    class and the parameter it was most likely meant to be (``difflib``). The class's deprecated parameters
    (``deprecated_parameters``, :mod:`sb3_dipper.common.deprecation`) are taken; one misspelt is named by its new form.

    :param algorithm: the class about to be built
    :param kwargs: its keyword arguments
    :param source: where the keywords came from, for the message (for example a YAML file)
    """
    parameters = constructor_parameters(algorithm)
    if any(parameter.kind is inspect.Parameter.VAR_KEYWORD for parameter in parameters.values()):
        return
    keywords = [name for name, parameter in parameters.items() if parameter.kind is not inspect.Parameter.POSITIONAL_ONLY]
    deprecated: Mapping[str, MovedParameter] = getattr(algorithm, "deprecated_parameters", {})
    for name in kwargs:
        if name not in keywords and name not in deprecated:
            close = difflib.get_close_matches(name, [*keywords, *deprecated], n=1)
            if not close:
                hint = f"see help({algorithm.__name__}) for its parameters"
            elif close[0] in deprecated:
                hint = f"did you mean {replacement_text(deprecated[close[0]])}?"
            else:
                hint = f"did you mean {close[0]!r}?"
            origin = f" (from {source})" if source else ""
            raise TypeError(f"{algorithm.__name__} got an unexpected keyword argument {name!r}{origin}; {hint}")


def check_dict_keys(parameter: str, given: Iterable[str], keys: Collection[str]) -> None:
    """Refuse a key of the dict parameter ``parameter`` (``demo_kwargs``) that is none of ``keys``: a ``TypeError``
    naming the parameter and the closest key, or every key when none is close."""
    for key in given:
        if key not in keys:
            close = difflib.get_close_matches(key, keys, n=1)
            hint = f"did you mean {close[0]!r}?" if close else f"its keys are {', '.join(keys)}"
            raise TypeError(f"{parameter} got an unexpected key {key!r}; {hint}")


class EnvGoalReward:
    """The env's ``compute_reward(achieved, desired, infos)`` called as SB3's ``HerReplayBuffer`` calls it (first env,
    a batch of goals), probed once at construction on a batch of 64 goal pairs.

    HER reaches ``compute_reward`` only at its first gradient step, after ``learning_starts``: a missing one, one
    without ``info`` or one that returns a single float for a batch failed there, inside SB3. The probe refuses such an
    env when the algorithm is built, naming what it needs.

    :param venv: the (vectorised) goal env
    :param algorithm: the algorithm's name, for the message
    """

    def __init__(self, venv: VecEnv, algorithm: str) -> None:
        self.venv = venv
        self.goal_dim = venv.observation_space["achieved_goal"].shape[0]  # type: ignore[index]
        need = (
            f"{algorithm} needs the goal env's compute_reward(achieved_goal, desired_goal, info), vectorised over a "
            "batch of goals as gymnasium-robotics envs have it (SB3's HerReplayBuffer relabels with it)"
        )
        # Goal pairs from far apart to identical: a sparse reward takes one value for reached goals and one for the rest.
        rng = np.random.default_rng(0)
        self.probe_achieved = rng.normal(size=(64, self.goal_dim)).astype(np.float32)
        spread = np.logspace(-4, 2, 64, dtype=np.float32)[:, None]
        desired = self.probe_achieved + spread * rng.normal(size=(64, self.goal_dim)).astype(np.float32)
        try:
            self.probe_rewards = self(self.probe_achieved, desired)
        except (AttributeError, TypeError) as error:
            raise ValueError(f"{need}, but calling it on a batch of 64 goal pairs failed: {error}") from error
        if self.probe_rewards.shape != (64,):
            raise ValueError(f"{need}, but a batch of 64 goal pairs gave rewards of shape {self.probe_rewards.shape}.")

    def __call__(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        infos: list[dict[str, Any]] = [{} for _ in range(achieved.shape[0])]
        rewards = self.venv.env_method("compute_reward", achieved, desired, infos, indices=[0])[0]
        return np.asarray(rewards, dtype=np.float64)


def check_compute_reward_for_her(model: Any) -> None:
    """Probe the env's ``compute_reward`` (:class:`EnvGoalReward`) of a flat ``model`` that relabels with SB3's
    ``HerReplayBuffer``; one without an env or without HER does not call it."""
    buffer_class = model.replay_buffer_class
    if model.env is not None and isinstance(buffer_class, type) and issubclass(buffer_class, HerReplayBuffer):
        EnvGoalReward(model.env, type(model).__name__)


GoalReachedFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


def sparse_goal_reached_fn(venv: VecEnv, algorithm: str = "Preference labelling") -> GoalReachedFn:
    """``goal_reached(achieved, desired)`` from the env's own vectorised ``compute_reward`` (:class:`EnvGoalReward`).

    A goal counts as reached where the reward equals the reward of an achieved goal equal to the desired one, so
    any sparse convention (-1/0 or 0/1) works. Dense rewards have no such level and are refused.

    :param venv: the (vectorised) goal env
    :param algorithm: the algorithm's name, for the message
    """
    rewards = EnvGoalReward(venv, algorithm)
    achieved = rewards.probe_achieved
    success_reward = rewards(achieved[:1], achieved[:1])[0]
    if np.unique(np.append(rewards.probe_rewards, success_reward)).size > 2:
        raise ValueError(
            "Preference labels need a sparse goal reward (one value when the goal is reached, one otherwise), "
            f"but compute_reward gave {np.unique(rewards.probe_rewards).size} different values on 64 goal pairs: "
            "is the reward dense? Use the env's sparse id (FetchReach-v4, not FetchReachDense-v4) or a -1/0 goal "
            "reward in compute_reward; HIER, HAC and SAGA take dense rewards."
        )

    def goal_reached(achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        flat_achieved = achieved.reshape(-1, rewards.goal_dim)
        flat_desired = np.broadcast_to(desired, achieved.shape).reshape(-1, rewards.goal_dim)
        reached = np.isclose(rewards(flat_achieved, flat_desired), success_reward)
        return reached.reshape(achieved.shape[:-1])

    return goal_reached


def _interval(low: float, high: float, low_open: bool, high_open: bool) -> str:
    if low == -math.inf and high == math.inf:
        return ""
    if high == math.inf:
        return f" {'>' if low_open else '>='} {low:g}"
    if low == -math.inf:
        return f" {'<' if high_open else '<='} {high:g}"
    return f" in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"


def _number(name: str, value: Any, expected: str) -> float:
    """``value`` as a float, for a setting that may arrive as a string from the zoo or a YAML file (``"1e-3"``)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating, str)):
        raise InvalidSetting(name, f"{name} must be {expected}, got {value!r} ({type(value).__name__})")
    try:
        return float(value)
    except ValueError:
        raise InvalidSetting(name, f"{name} must be {expected}, got {value!r}") from None


def as_int(name: str, value: Any, minimum: int, reason: str = "") -> int:
    """An integer setting, converted and checked at construction.

    Settings reach the constructors from the zoo's ``-params``, Optuna and YAML (``5e4``, ``!!float 5e4``, ``20.0``,
    ``"20"``); numpy needs real ints, and its error would only come deep in training. Whole numbers of any of these
    types become ints; anything else (``2.5``, ``"abc"``, ``True``) and values below ``minimum`` are refused.

    :param name: the parameter's name, for the message
    :param value: the value given
    :param minimum: the smallest allowed value
    :param reason: why (appended to the message)
    """
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        integer = int(value)
    else:
        expected = f"a whole number (an integer >= {minimum})"
        number = _number(name, value, expected)
        if not number.is_integer():
            raise InvalidSetting(name, f"{name} must be {expected}, got {value!r}")
        integer = int(number)
    if integer < minimum:
        raise InvalidSetting(name, f"{name} must be at least {minimum}, got {value!r}{f' ({reason})' if reason else ''}")
    return integer


def as_optional_int(name: str, value: Any, minimum: int, reason: str = "") -> int | None:
    """:func:`as_int` for a setting whose ``None`` means "the default" (for example, read from the env)."""
    return None if value is None else as_int(name, value, minimum, reason)


def as_train_freq(value: Any) -> int | tuple[int, str]:
    """SB3's ``train_freq`` (``n`` steps, or ``(n, "step" | "episode")``) with ``n`` checked by :func:`as_int`."""
    if isinstance(value, (tuple, list)) and len(value) == 2:
        return as_int("train_freq", value[0], 1), value[1]
    return as_int("train_freq", value, 1)


def as_float(
    name: str,
    value: Any,
    low: float = -math.inf,
    high: float = math.inf,
    *,
    low_open: bool = False,
    high_open: bool = False,
    reason: str = "",
) -> float:
    """A real-valued setting, converted to float and refused unless finite and inside its interval.

    :param name: the parameter's name, for the message
    :param value: the value given
    :param low: lower bound of the allowed interval
    :param high: upper bound of the allowed interval
    :param low_open: whether ``low`` itself is excluded
    :param high_open: whether ``high`` itself is excluded
    :param reason: why (appended to the message)
    """
    interval = _interval(low, high, low_open, high_open)
    number = _number(name, value, f"a finite number{interval}")
    inside = (low < number if low_open else low <= number) and (number < high if high_open else number <= high)
    if not (math.isfinite(number) and inside):
        raise InvalidSetting(
            name, f"{name} must be a finite number{interval}, got {value!r}{f' ({reason})' if reason else ''}"
        )
    return number


def as_learning_rate(name: str, value: Any) -> float | Callable[[float], float]:
    """A learning rate: a number >= 0 (``"1e-3"``, as YAML reads ``1e-3`` without ``!!float``, becomes ``0.001``; 0 is a
    model that no longer learns, as rl-zoo3's ``enjoy`` loads one) or, where SB3 takes one, a schedule of the remaining
    progress (a callable, kept as it is)."""
    return value if callable(value) else as_float(name, value, 0.0)


def as_entropy_coefficient(name: str, value: Any) -> str | float:
    """SAC's entropy coefficient: ``"auto"`` or ``"auto_<initial value > 0>"`` learns it, a number >= 0 fixes it (a
    negative one would make SAC minimise entropy)."""
    if isinstance(value, str) and value.startswith("auto"):
        initial = value.removeprefix("auto").removeprefix("_")
        if value != "auto" and (not value.startswith("auto_") or not _is_positive_number(initial)):
            raise InvalidSetting(name, f'{name} must be "auto", "auto_<initial value > 0>" or a number >= 0, got {value!r}')
        return value
    expected = 'a finite number >= 0, "auto" or "auto_<initial value > 0>"'
    number = _number(name, value, expected)
    if not (math.isfinite(number) and number >= 0.0):
        raise InvalidSetting(name, f"{name} must be {expected}, got {value!r}")
    return number


def _is_positive_number(text: str) -> bool:
    try:
        return math.isfinite(float(text)) and float(text) > 0.0
    except ValueError:
        return False


def as_optional_float(name: str, value: Any, low: float = -math.inf, high: float = math.inf, **kwargs: Any) -> float | None:
    """:func:`as_float` for a setting whose ``None`` means "off" or "the default"."""
    return None if value is None else as_float(name, value, low, high, **kwargs)


def as_bool(name: str, value: Any) -> bool:
    """An on/off setting: ``True`` or ``False`` (numpy's booleans included), never a string such as ``"False"``, which
    Python would take as on."""
    if not isinstance(value, (bool, np.bool_)):
        raise InvalidSetting(name, f"{name} must be True or False, got {value!r}")
    return bool(value)


def as_demo_path(name: str, value: Any) -> str | None:
    """Where demonstrations come from: ``None`` (none), or a path as a string (a ``pathlib.Path`` is taken as its
    string, which saves with the model as JSON): an npz file, a Minari dataset directory, ``"auto"`` or
    ``"auto:dart<N>"``. An empty string would be read as the current directory."""
    if value is None:
        return None
    if isinstance(value, os.PathLike):
        value = os.fspath(value)
    if not isinstance(value, str) or not value:
        raise InvalidSetting(
            name,
            f"{name} must be an npz file, a Minari dataset directory, 'auto' or 'auto:dart<N>' (a str or a "
            f"pathlib.Path), or None for no demonstrations; got {value!r}",
        )
    return value


def as_choice(name: str, value: Any, choices: tuple[str, ...]) -> str:
    """A setting that names one of ``choices`` (``value_reg``, ``planning``)."""
    if value not in choices:
        raise InvalidSetting(name, f"Unknown {name} {value!r}: choose one of {choices}")
    return value


# What a HerReplayBuffer takes from replay_buffer_kwargs (the algorithm gives it its size, spaces, env and device).
HER_BUFFER_KEYS = (
    "n_sampled_goal",
    "goal_selection_strategy",
    "copy_info_dict",
    "handle_timeout_termination",
    "optimize_memory_usage",
)


def checked_her_kwargs(name: str, kwargs: Mapping[str, Any]) -> dict[str, Any]:
    """A ``HerReplayBuffer``'s keyword arguments (``replay_buffer_kwargs``) checked: known keys, ``n_sampled_goal`` a
    whole number >= 0 (SB3 relabels ``n / (n + 1)`` of the sampled transitions: below 0 it would relabel every one,
    and the env's own goals would never be trained on) and ``goal_selection_strategy`` one of SB3's strategies.

    :param name: the parameter, for the messages (``replay_buffer_kwargs``)
    :param kwargs: its value
    """
    check_dict_keys(name, kwargs, HER_BUFFER_KEYS)
    settings = dict(kwargs)
    if "n_sampled_goal" in settings:
        settings["n_sampled_goal"] = as_int(f"{name}['n_sampled_goal']", settings["n_sampled_goal"], 0)
    strategy = settings.get("goal_selection_strategy")
    if isinstance(strategy, str):
        as_choice(f"{name}['goal_selection_strategy']", strategy, ("future", "final", "episode"))
    return settings


def check_flat_sac_settings(model: Any) -> None:
    """Coerce or refuse the settings of a flat SB3 SAC (DAC, SACDemo) in place: they may arrive as floats or strings (zoo
    ``-params``, YAML ``5e4``), so they are checked when the model is built or loaded, not in training.

    :param model: the SAC whose ``buffer_size``, ``learning_starts``, ``batch_size``, ``tau``, ``gamma``,
        ``train_freq``, ``gradient_steps`` and ``target_update_interval`` are checked
    """
    model.buffer_size = as_int("buffer_size", model.buffer_size, 1)
    model.learning_starts = as_int("learning_starts", model.learning_starts, 0)
    model.batch_size = as_int("batch_size", model.batch_size, 1)
    model.tau = as_float("tau", model.tau, 0.0, 1.0, low_open=True)
    # SB3's SAC range: gamma = 0 (a bandit) is meaningful for a flat learner.
    model.gamma = as_float("gamma", model.gamma, 0.0, 1.0)
    model.train_freq = as_train_freq(model.train_freq)
    model.gradient_steps = as_int("gradient_steps", model.gradient_steps, -1, "-1: as many as environment steps collected")
    model.target_update_interval = as_int("target_update_interval", model.target_update_interval, 1)
    model.ent_coef = as_entropy_coefficient("ent_coef", model.ent_coef)


def policy_class_and_goal_env(model: Any, policy: Any, env: Any, verbose: int) -> tuple[Any, Any]:
    """A constructor's ``policy`` and ``env`` as SB3's base class should get them: a policy alias mapped to its class by
    the model's ``policy_aliases`` (SB3 refuses the string ``"MlpPolicy"`` for Dict observations, and goal envs are
    Dict), an env id made into an env and refused unless it is a goal env, both errors naming the algorithm.

    :param model: the algorithm being constructed (its class names it in errors)
    :param policy: the constructor's ``policy``: a class or an alias
    :param env: the constructor's ``env``: an env, an env id or ``None``
    :param verbose: the constructor's ``verbose``, for SB3's ``maybe_make_env``
    """
    algorithm = type(model).__name__
    if isinstance(policy, str):
        if policy not in model.policy_aliases:
            raise ValueError(f"{algorithm} has no policy {policy!r}; choose one of {sorted(model.policy_aliases)}")
        policy = model.policy_aliases[policy]
    elif not (isinstance(policy, type) and issubclass(policy, tuple(model.policy_aliases.values()))):
        # Another algorithm's policy class (SB3's sac.MultiInputPolicy) would fail deep inside the model's set-up.
        aliases = sorted(model.policy_aliases)
        classes = sorted({cls.__name__ for cls in model.policy_aliases.values()})
        example = "MultiInputPolicy" if "MultiInputPolicy" in aliases else aliases[0]
        raise TypeError(
            f"{algorithm}'s policy must be one of {aliases} or a subclass of {' or '.join(classes)}, got {policy!r}: "
            f"pass the alias string, e.g. {algorithm}({example!r}, env)"
        )
    if env is not None:
        env = maybe_make_env(env, verbose)
        check_goal_observation_space(env.observation_space, algorithm)
    return policy, env
