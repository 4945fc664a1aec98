"""Loading a saved model and giving a model an env: SB3's ``save``, ``load`` and ``set_env`` with our algorithms' checks.

:class:`CheckedLoading` sits between each of our algorithms and its SB3 base class. It

* records the saving class's name in the zip's data (``saved_by``), and ``load`` refuses a file that another class
  saved with a ``ValueError`` naming that class (SB3 alone fails later, with a ``KeyError`` or a parameter mismatch);
  a file without ``saved_by`` (SB3's ``SAC``, sb3-contrib's ``TQC``, another library's class) is refused too, naming
  the algorithm whose policy it holds (:func:`saving_algorithms`), unless it holds the loading class's own settings
  (a file of sb3-dipper 0.1.0, which wrote no ``saved_by``);
* checks the settings of a loaded model as its constructor checks them (:meth:`CheckedLoading._check_settings`, run
  by ``_setup_model``, which both call): a value out of range in the file (``beta = -1``, ``planning = "bogus"``) or
  given to ``load`` is refused with an error that names the parameter and the file;
* refuses a file whose networks, optimizer states or torch variables hold NaN or infinite values, naming the tensor
  (a model saved after its training diverged would fail only at its first prediction, inside torch);
* refuses an entropy coefficient given to ``load`` that the saved model's state cannot take
  (:func:`check_entropy_coefficient`);
* refuses an env whose time limit differs from the episode length the model's buffers were sized for
  (``max_episode_steps``), at ``load`` and at ``set_env``: trajectories would be cut into pieces without a word.
  ``load(path, env=env, max_episode_steps=N)`` rebuilds the model for the env's N-step episodes;
* takes the constructor parameters a class has deprecated (moved into a dict parameter, its ``deprecated_parameters``)
  at construction and at ``load``, and loads files saved before they moved (:mod:`sb3_dipper.common.deprecation`);
* rebuilds a model around its trained parameters (:meth:`CheckedLoading._rebuild_keeping_parameters`), with which
  ``set_env`` turns a model loaded without an env (predict-only buffers) into one that trains with its configured
  buffers, so SB3's ``model = X.load(path); model.set_env(env); model.learn(n, reset_num_timesteps=False)`` works.
"""

from __future__ import annotations

import base64
import functools
import io
import json
import pathlib
import pickletools
import zipfile
from collections.abc import Callable, Mapping
from typing import Any, ClassVar, TypeVar

import gymnasium as gym
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.save_util import json_to_data, open_path, recursive_getattr, recursive_setattr
from stable_baselines3.common.type_aliases import GymEnv
from stable_baselines3.common.utils import check_for_correct_spaces
from stable_baselines3.common.vec_env import VecEnv

from sb3_dipper.common.deprecation import (
    DeprecatedAttribute,
    MovedParameter,
    completed_groups,
    fold_saved_parameters,
    move_deprecated_parameters,
    taking_deprecated_parameters,
)
from sb3_dipper.common.files import save_model_atomically
from sb3_dipper.common.validation import (
    InvalidSetting,
    as_int,
    as_learning_rate,
    check_keyword_arguments,
    constructor_parameters,
)

SelfCheckedLoading = TypeVar("SelfCheckedLoading", bound="CheckedLoading")


SetEnv = TypeVar("SetEnv", bound=Callable[..., None])


def unchanged_on_failure(set_env: SetEnv) -> SetEnv:
    """Make a model's ``set_env`` all or nothing: if it raises, the model's attributes are put back as they were.

    ``set_env`` on a model loaded without an env rebuilds it for the env (``_setup_model``) around its networks; a
    check that fails partway (the demonstrations moved, a dense reward) must not leave freshly initialised networks in
    place of the trained ones. The rebuild assigns new objects (networks, buffers, option layer) and mutates none of
    the old ones, so the old attributes are the old model.
    """

    @functools.wraps(set_env)
    def all_or_nothing(self: Any, *args: Any, **kwargs: Any) -> None:
        attributes = dict(self.__dict__)
        try:
            set_env(self, *args, **kwargs)
        except BaseException:
            self.__dict__.clear()
            self.__dict__.update(attributes)
            raise

    return all_or_nothing  # type: ignore[return-value]


def saved_data_fields(path: str | pathlib.Path | io.BufferedIOBase) -> dict[str, Any]:
    """The top-level fields of a saved model's data, as JSON: serialised objects stay encoded (nothing is unpickled).

    ``{}`` when the file is no SB3 zip or has no data; SB3's ``load`` then reports the problem itself.
    """
    if isinstance(path, io.BufferedIOBase):
        start = path.tell()
        try:
            return _read_data_fields(path)
        finally:
            path.seek(start)
    with open_path(path, "r", suffix="zip") as file:
        return _read_data_fields(file)


def _saved_spaces(fields: dict[str, Any], custom_objects: dict[str, Any] | None) -> tuple[Any, Any] | None:
    """The saved observation and action spaces, decoded as SB3's ``load`` decodes them (``None`` if either is missing
    or cannot be decoded: SB3's ``load`` then reports the problem itself)."""
    if "observation_space" not in fields or "action_space" not in fields:
        return None
    encoded = {name: fields[name] for name in ("observation_space", "action_space")}
    decoded = json_to_data(json.dumps(encoded), custom_objects=custom_objects)
    spaces = decoded.get("observation_space"), decoded.get("action_space")
    return spaces if all(isinstance(space, gym.spaces.Space) for space in spaces) else None


def _read_data_fields(file: io.BufferedIOBase) -> dict[str, Any]:
    try:
        with zipfile.ZipFile(file) as archive:
            if "data" not in archive.namelist():
                return {}
            fields = json.loads(archive.read("data").decode())
    except (zipfile.BadZipFile, json.JSONDecodeError):
        return {}
    return fields if isinstance(fields, dict) else {}


def saving_algorithms(fields: dict[str, Any]) -> tuple[list[type[BaseAlgorithm]], str | None]:
    """Which algorithms may have saved a model whose data has no ``saved_by``, read from its policy class without
    unpickling anything.

    :param fields: the saved data (:func:`saved_data_fields`)
    :return: the algorithms imported in this process that declare the saved policy class among their own
        ``policy_aliases`` (SB3's ``SAC`` for an SB3 ``SAC`` zip; ``A2C``, ``PPO`` and sb3-contrib's ``TRPO`` share one),
        and the policy class as ``module.Name`` (``None`` where the data does not name it)
    """
    policy_class = fields.get("policy_class")
    name = _pickled_class_name(policy_class) if isinstance(policy_class, dict) else None
    if name is None:
        return [], None
    algorithms = [
        algorithm
        for algorithm in _algorithm_classes()
        # Only the class that declares the aliases: subclasses of SAC (ours among them) inherit SAC's.
        if "policy_aliases" in vars(algorithm)
        and not issubclass(algorithm, CheckedLoading)
        and any(f"{policy.__module__}.{policy.__qualname__}" == name for policy in algorithm.policy_aliases.values())
    ]
    return sorted(algorithms, key=_public_name), name


def _public_name(algorithm: type[BaseAlgorithm]) -> str:
    """``stable_baselines3.SAC``, ``sb3_contrib.TQC``: where a user imports the algorithm from."""
    return f"{algorithm.__module__.partition('.')[0]}.{algorithm.__name__}"


def _other_librarys_file(cls: type[BaseAlgorithm], path: Any, fields: dict[str, Any]) -> ValueError | None:
    """The error for a file without ``saved_by`` that another library's algorithm saved, ``None`` for a file of
    sb3-dipper from before ``saved_by`` existed: that one holds settings of ``cls`` (``option_steps``, ...) that neither
    SB3's base classes nor the algorithms its policy class points to take."""
    savers, policy = saving_algorithms(fields)
    others: list[type] = [*savers, BaseAlgorithm, OffPolicyAlgorithm, OnPolicyAlgorithm]
    own_settings = set(constructor_parameters(cls)).difference(*map(constructor_parameters, others))
    if own_settings & fields.keys():
        return None
    if len(savers) == 1:
        saver, loader = _public_name(savers[0]), f"{_public_name(savers[0])}.load"
    elif savers:
        saver, loader = " or ".join(map(_public_name, savers)), "the one that saved it"
    else:
        saver, loader = "another library's algorithm", "the class that saved it"
    return ValueError(
        f"{path} was saved by {saver} (its policy is {policy or 'not named in the file'}), not by an sb3-dipper "
        f"algorithm: load it with {loader}, not {cls.__name__}.load ({cls.__name__}.load reads the files "
        f"{cls.__name__}.save writes)"
    )


def _algorithm_classes() -> list[type[BaseAlgorithm]]:
    """Every subclass of SB3's ``BaseAlgorithm`` imported so far."""
    found: list[type[BaseAlgorithm]] = []
    pending = list(BaseAlgorithm.__subclasses__())
    while pending:
        algorithm = pending.pop()
        if algorithm not in found:
            found.append(algorithm)
            pending.extend(algorithm.__subclasses__())
    return found


def _pickled_class_name(serialized: dict[str, Any]) -> str | None:
    """``module.Name`` of a class SB3 saved by reference (a cloudpickle global), read from the pickle's opcodes, which
    are listed, not run; ``None`` for anything else (a class saved by value, a broken field)."""
    strings: list[str] = []
    try:
        for opcode, argument, _ in pickletools.genops(base64.b64decode(serialized.get(":serialized:", ""))):
            if opcode.name == "STACK_GLOBAL" and len(strings) >= 2:
                module, name = strings[-2], strings[-1]
                break
            if opcode.name == "GLOBAL":
                module, _, name = str(argument).partition(" ")
                break
            if isinstance(argument, str):
                strings.append(argument)
        else:
            return None
    except ValueError:  # not base64, or not a pickle
        return None
    # A class saved by value starts with cloudpickle's own globals; its module is then not the class's.
    return f"{module}.{name}" if module == serialized.get("__module__") else None


def _invalid_setting_message(algorithm: str, path: Any, error: InvalidSetting, kwargs: dict[str, Any]) -> str:
    """Where the refused setting of a loaded model came from (the file, or ``load``'s keywords) and how to fix it."""
    if error.setting in kwargs:
        return f"{algorithm}.load({path}, {error.setting}={kwargs[error.setting]!r}): {error}"
    return (
        f"{path} holds a setting {algorithm}'s constructor refuses: {error}. Was the file edited? Load it with a valid "
        f"value, {algorithm}.load(path, {error.setting}=...), and save it again, or load another copy of the model."
    )


def first_non_finite_tensor(model: BaseAlgorithm) -> str | None:
    """The name of the first tensor ``save`` writes (networks, optimizer states, torch variables) that holds NaN or
    infinite values, such as ``lower.policy.actor.mu.weight``; ``None`` if every one is finite."""
    state_dicts, variables = model._get_torch_save_params()
    named = [(name, recursive_getattr(model, name).state_dict()) for name in state_dicts]
    named += [(name, recursive_getattr(model, name)) for name in variables]
    for name, value in named:
        for tensor_name, tensor in _named_tensors(name, value):
            if tensor.is_floating_point() and not bool(th.isfinite(tensor).all()):
                return tensor_name
    return None


def _named_tensors(name: str, value: Any) -> list[tuple[str, th.Tensor]]:
    """The tensors in ``value`` (a tensor, or dicts and lists of them: state dicts, optimizer states), each named by
    its path from ``name``."""
    if isinstance(value, th.Tensor):
        return [(name, value)]
    if isinstance(value, dict):
        return [found for key, item in value.items() for found in _named_tensors(f"{name}.{key}", item)]
    if isinstance(value, (list, tuple)):
        return [found for index, item in enumerate(value) for found in _named_tensors(f"{name}.{index}", item)]
    return []


def check_entropy_coefficient(name: str, saved: Any, given: Any, where: str) -> None:
    """Refuse an entropy coefficient given to ``load`` that the saved model's state would override or could not hold.

    SB3's SAC learns its coefficient (``"auto"``, ``"auto_<initial value>"``) with an optimizer of its own, or keeps a
    fixed one as a tensor; ``load`` restores either from the file. A learned one given for a fixed one (or the other
    way round) finds no optimizer state to restore (SB3 fails with ``AttributeError: 'NoneType' object has no attribute
    'load_state_dict'``), and another fixed value would be replaced by the saved one without a word. A learned one for
    a learned one is kept: the file restores the learned value, whatever the initial one.

    :param name: the setting (``ent_coef``, ``high_ent_coef``)
    :param saved: its value in the file
    :param given: the value given to ``load``
    :param where: the call, for the message
    """
    saved_learns, given_learns = (str(value).startswith("auto") for value in (saved, given))
    if saved_learns and given_learns:
        return
    if not saved_learns and not given_learns and float(saved) == float(given):
        return
    kind = "learns its entropy coefficient" if saved_learns else "keeps a fixed entropy coefficient"
    raise ValueError(
        f"{where}: the saved model {kind} ({name}={saved!r}), which the file restores; {name}={given!r} cannot take "
        f"its place when loading. Leave {name} out to go on with the saved one, or train a new model with "
        f"{name}={given!r}."
    )


def env_time_limit(env: VecEnv) -> int | None:
    """The env's time limit (``spec.max_episode_steps``), ``None`` if it has none."""
    spec = env.get_attr("spec", indices=[0])[0]
    length = getattr(spec, "max_episode_steps", None)
    return None if length is None else int(length)


def check_time_limit(env: VecEnv, episode_length: int | None, algorithm: str, fix: str) -> None:
    """Refuse an env whose time limit is not the episode length a model's buffers are sized for.

    :param env: the new env
    :param episode_length: the model's ``max_episode_steps`` (``None``: it sizes nothing by episodes)
    :param algorithm: the algorithm's name, for the message
    :param fix: how to rebuild the model for the env's episodes, with ``{limit}`` where the env's time limit goes
    """
    limit = env_time_limit(env)
    if limit is None or episode_length is None or limit == episode_length:
        return
    raise ValueError(
        f"This {algorithm} model was built for {episode_length}-step episodes (max_episode_steps={episode_length}), "
        f"but the env's time limit is {limit} steps: its episode buffers and horizon are sized for {episode_length} "
        f"steps, so the env's episodes would be cut into pieces. Use an env with a {episode_length}-step time limit, or "
        f"{fix.format(limit=limit)}."
    )


class CheckedLoading(BaseAlgorithm):
    """SB3's ``save``, ``load`` and ``set_env``, with the checks described in :mod:`sb3_dipper.common.loading`."""

    # The class that saved the model: written by save, checked by load.
    saved_by: str
    # The episode length the model's buffers are sized for, also read from a saved file (None: sized by no episodes).
    max_episode_steps: int | None = None
    # Constructor parameters that moved into a dict parameter, by their old names (:mod:`sb3_dipper.common.deprecation`).
    deprecated_parameters: ClassVar[Mapping[str, MovedParameter]] = {}

    @classmethod
    def setting_groups(cls) -> set[str]:
        """The dict parameters whose keys are settings of their own (``demo_kwargs``; those that took deprecated
        parameters in): one given to ``load`` changes the keys it names of the saved one, and a trial of the zoo's
        tuning those of the YAML entry's."""
        return {moved.group for moved in cls.deprecated_parameters.values()}

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """Let the class's constructor take its deprecated parameters (out of its signature), and give its models their
        old attributes, which warn."""
        super().__init_subclass__(**kwargs)
        if "__init__" in vars(cls):
            cls.__init__ = taking_deprecated_parameters(vars(cls)["__init__"])  # type: ignore[method-assign]
        for name, moved in vars(cls).get("deprecated_parameters", {}).items():
            if name not in vars(cls):
                attribute = DeprecatedAttribute.of(moved)
                attribute.__set_name__(cls, name)
                setattr(cls, name, attribute)

    def __new__(cls, *args: Any, **kwargs: Any) -> Any:
        """Refuse a misspelt keyword with a "did you mean" (:func:`~sb3_dipper.common.validation.check_keyword_arguments`).

        Python raises its bare ``TypeError`` for an unknown keyword before ``__init__`` runs, so the check sits here,
        the one place every construction passes (code, the zoo's YAML and ``-params``, Optuna), and each ``__init__``
        keeps SB3's explicit signature.
        """
        check_keyword_arguments(cls, kwargs)
        return super().__new__(cls)

    def _check_settings(self) -> None:
        """Check the model's settings and convert them to what training needs (``"5e4"`` becomes ``50000``), raising
        :class:`~sb3_dipper.common.validation.InvalidSetting` for a value out of range.

        Each algorithm extends it with its own settings (calling ``super()``), and calls it first thing in
        ``_setup_model``: the constructor builds its model there, and so does ``load``, after it has set the
        settings read from the file (and those given to ``load``), so the one set of checks covers both.
        """
        fold_saved_parameters(self, self.deprecated_parameters)
        # SB3's BaseAlgorithm keeps this setting under a private name.
        self._stats_window_size = as_int("stats_window_size", self._stats_window_size, 1)
        self.learning_rate = as_learning_rate("learning_rate", self.learning_rate)

    def save(self, path: Any, exclude: Any = None, include: Any = None) -> None:
        """SB3's ``save``; the data also names the saving class, so that loading with another class fails clearly.

        To a path, the zip is written under a temporary name and renamed into place: a run killed while saving leaves
        the previous complete zip (or none), never a truncated one.
        """
        self.saved_by = type(self).__name__
        save_model_atomically(super().save, path, exclude, include)

    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfCheckedLoading],
        path: str | pathlib.Path | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        **kwargs: Any,
    ) -> SelfCheckedLoading:
        """SB3's ``load``; refuses a file another algorithm saved, a keyword that is neither a parameter nor a saved
        attribute (a misspelt one would change nothing), a setting the constructor would refuse (from the file or
        given here), and an env whose time limit is not the model's episode length (pass ``max_episode_steps=`` the
        env's limit to rebuild the model for the env's episodes). A dict parameter given here that holds deprecated
        parameters (``demo_kwargs``) replaces the saved one's keys, not the whole dict.
        """
        fields = saved_data_fields(path)
        saved_by = fields.get("saved_by")
        if saved_by is not None and saved_by != cls.__name__:
            raise ValueError(f"{path} was saved by {saved_by}; load it with {saved_by}.load, not {cls.__name__}.load")
        # A file without saved_by from another library: SB3 alone would fail on its first missing attribute or
        # parameter, with an AssertionError or a KeyError.
        if saved_by is None and fields and (error := _other_librarys_file(cls, path, fields)) is not None:
            raise error
        # SB3 sets every keyword as an attribute: one that is neither a parameter nor a saved attribute (a misspelt
        # learning_starts) would change nothing, silently.
        unknown = {name: value for name, value in kwargs.items() if name not in fields}
        check_keyword_arguments(cls, unknown, f"{cls.__name__}.load({path})")
        kwargs = cls._with_deprecated_parameters_moved(fields, kwargs)
        for name in constructor_parameters(cls):
            if name.endswith("ent_coef") and name in kwargs and name in fields:
                check_entropy_coefficient(name, fields[name], kwargs[name], f"{cls.__name__}.load({path}, ...)")
        if env is not None:
            env = cls._wrap_env(env, int(fields.get("verbose", 0)))
            # SB3 compares the spaces inside its load, after the time limit is checked here: an env of another task
            # would be told to change its episode length first, and then that its spaces differ.
            saved_spaces = _saved_spaces(fields, custom_objects)
            if saved_spaces is not None:
                check_for_correct_spaces(env, *saved_spaces)
            check_time_limit(
                env,
                kwargs.get("max_episode_steps", fields.get("max_episode_steps")),
                cls.__name__,
                f"rebuild it for the env's episodes with {cls.__name__}.load(path, env=env, max_episode_steps={{limit}})",
            )
        try:
            model = super().load(path, env, device, custom_objects, print_system_info, force_reset, **kwargs)
        except InvalidSetting as error:
            raise InvalidSetting(error.setting, _invalid_setting_message(cls.__name__, path, error, kwargs)) from None
        # Torch would only fail later, inside Normal(...) at the first prediction, naming neither file nor tensor.
        damaged = first_non_finite_tensor(model)
        if damaged is not None:
            raise ValueError(
                f"{path} holds NaN or infinite values in {damaged}: the model was saved after its training diverged, "
                "or the file is damaged. Load an earlier checkpoint of the run."
            )
        return model  # type: ignore[return-value]

    @classmethod
    def _with_deprecated_parameters_moved(cls, fields: dict[str, Any], kwargs: dict[str, Any]) -> dict[str, Any]:
        """``load``'s keywords with the deprecated parameters moved into their groups (with a warning), each group given
        on top of the saved one: ``load(path, bc_coef=0.01)`` changes that key only."""
        kwargs = move_deprecated_parameters(cls.__name__, cls.deprecated_parameters, kwargs)
        # A group holding objects that are no JSON was pickled whole; it is replaced, as SB3 replaces any setting.
        readable = {name: value for name, value in fields.items() if not (isinstance(value, dict) and ":serialized:" in value)}
        return completed_groups(cls.setting_groups(), kwargs, readable)

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        """SB3's ``set_env``; refuses an env whose time limit is not the model's episode length."""
        env = self._wrap_env(env, self.verbose)
        # Spaces first, as in load: an env of another task needs no advice on its episode length.
        check_for_correct_spaces(env, self.observation_space, self.action_space)
        check_time_limit(
            env,
            self.max_episode_steps,
            type(self).__name__,
            f"rebuild the model for them with {type(self).__name__}.load(path, env=env, max_episode_steps={{limit}})",
        )
        super().set_env(env, force_reset)

    def _rebuild_keeping_parameters(self) -> None:
        """Build the model anew for its current env (``_setup_model``), keeping its networks, optimizers and torch
        variables, as ``load`` puts them back. Attributes that are saved with the model stay as they are."""
        parameters = self.get_parameters()
        _, variable_names = self._get_torch_save_params()
        variables = {name: recursive_getattr(self, name) for name in variable_names}
        self._setup_model()
        self.set_parameters(parameters, exact_match=True, device=self.device)  # type: ignore[arg-type]
        for name, value in variables.items():
            # As load: set .data, so that optimizers keep the new tensor they hold (None: e.g. SAC's fixed ent_coef).
            if value is not None:
                recursive_setattr(self, f"{name}.data", value.data)
