"""Constructor parameters that moved into a dict parameter, still taken by their old names with a warning.

A class lists them in its ``deprecated_parameters`` (:class:`~sb3_dipper.common.loading.CheckedLoading`), each with
the group (a dict parameter) and key it went to: DIPPER's ``planning`` is ``planner_kwargs["mode"]``, a hierarchical
algorithm's ``bc_coef`` is ``demo_kwargs["bc_coef"]``. The old names are out of the signature (``help()``, the docs),
yet

* given to the constructor (code, the zoo's YAML and ``-params``, Optuna) or to ``load``, a value goes to its key,
  with a ``DeprecationWarning`` that names the replacement (:func:`move_deprecated_parameters`); the old name wins over
  the key of a group given beside it, as a ``-params`` override wins over the YAML entry;
* a model saved before the move (the old attributes in its data) loads into the new form without a word
  (:func:`fold_saved_parameters`);
* reading or setting the old attribute of a model warns and reads or writes the value where it lives now
  (:class:`DeprecatedAttribute`).
"""

from __future__ import annotations

import functools
import sys
import warnings
from collections.abc import Callable, Collection, Iterable, Mapping
from typing import Any, NamedTuple


class MovedParameter(NamedTuple):
    """Where a deprecated constructor parameter went.

    :param group: the dict parameter that takes it now (``demo_kwargs``)
    :param key: its key there (``bc_coef``)
    :param holder: the model attribute that keeps the value as its attribute ``key`` once the model is built (DIPPER's
        ``planner``: ``model.planner.mode``); ``None``: the group itself does (``model.demo_kwargs["bc_coef"]``)
    :param none_is_unset: ``None`` given for it means "not given" (its default was ``None``, standing for the group's
        own default)
    """

    group: str
    key: str
    holder: str | None = None
    none_is_unset: bool = False


def replacement_text(moved: MovedParameter) -> str:
    """The new form, for messages: ``demo_kwargs['bc_coef']``."""
    return f"{moved.group}[{moved.key!r}]"


def warn_deprecated(message: str) -> None:
    """A ``DeprecationWarning`` that points at the first caller outside this package (the user's line, which Python's
    default filters then show when it is in ``__main__``), however many of the package's frames lie between."""
    frame, stacklevel = sys._getframe(0), 1
    while frame.f_back is not None and frame.f_globals.get("__name__", "").startswith("sb3_dipper."):
        frame, stacklevel = frame.f_back, stacklevel + 1
    warnings.warn(message, DeprecationWarning, stacklevel=stacklevel)


def move_deprecated_parameters(
    owner: str, declared: Mapping[str, MovedParameter], kwargs: Mapping[str, Any]
) -> dict[str, Any]:
    """``kwargs`` with the deprecated parameters among them moved into their groups (new dicts: the caller's stay as
    they were), with one ``DeprecationWarning`` per group naming the replacement.

    :param owner: the class, for the message
    :param declared: its deprecated parameters
    :param kwargs: the keyword arguments given
    """
    given = {
        name: value
        for name, value in kwargs.items()
        if name in declared and not (value is None and declared[name].none_is_unset)
    }
    moved_kwargs = {name: value for name, value in kwargs.items() if name not in declared}
    for group in dict.fromkeys(moved.group for name, moved in declared.items() if name in given):
        names = [name for name in declared if name in given and declared[name].group == group]
        replacement = {declared[name].key: given[name] for name in names}
        warn_deprecated(
            f"{owner}'s {', '.join(names)} {'is' if len(names) == 1 else 'are'} deprecated: pass {group}={replacement!r} "
            "instead"
        )
        moved_kwargs[group] = {**(moved_kwargs.get(group) or {}), **replacement}
    return moved_kwargs


def completed_groups(groups: Collection[str], given: Mapping[str, Any], base: Mapping[str, Any]) -> dict[str, Any]:
    """``given`` with each of ``groups`` among them (``demo_kwargs``) completed by the keys of the same group in
    ``base`` that it does not name: set over ``base`` (a saved model's settings, a zoo entry), a group changes the keys
    it names, as the parameters it holds did one by one. A group that is no dict in ``base`` is replaced whole.

    :param groups: the dict parameters given key by key (a class's ``setting_groups``)
    :param given: the keyword arguments given (a group given as ``None`` keeps ``base``'s)
    :param base: the settings they are set over
    """
    return {
        name: {**base[name], **(value or {})}
        if name in groups and isinstance(base.get(name), dict) and (value is None or isinstance(value, dict))
        else value
        for name, value in given.items()
    }


def in_new_form(hyperparameters: Mapping[str, Any], algorithms: Iterable[type]) -> dict[str, Any]:
    """``hyperparameters`` with the deprecated parameters of any of ``algorithms`` moved into their groups, without a
    warning: the same settings in today's form, so that hyperparameters recorded in the old form (a run's
    ``config.yml``) compare equal to the same ones given in the new."""
    declared = {
        name: moved for algorithm in algorithms for name, moved in getattr(algorithm, "deprecated_parameters", {}).items()
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return move_deprecated_parameters("", declared, hyperparameters)


def taking_deprecated_parameters(init: Callable[..., None]) -> Callable[..., None]:
    """``init`` (a constructor) that also takes the deprecated parameters of the object's class (its
    ``deprecated_parameters``), moved into their groups; the signature stays ``init``'s own (``functools.wraps``)."""

    @functools.wraps(init)
    def init_taking_deprecated_parameters(self: Any, *args: Any, **kwargs: Any) -> None:
        declared = type(self).deprecated_parameters
        if declared.keys() & kwargs.keys():
            kwargs = move_deprecated_parameters(type(self).__name__, declared, kwargs)
        init(self, *args, **kwargs)

    return init_taking_deprecated_parameters


def fold_saved_parameters(model: Any, declared: Mapping[str, MovedParameter]) -> None:
    """Move the deprecated parameters that ``load`` set as attributes of ``model`` (read from a file saved before they
    moved) into their groups, under the keys the group already has (given to ``load``), without a warning."""
    for name, moved in declared.items():
        if name in vars(model):
            value = vars(model).pop(name)
            setattr(model, moved.group, {moved.key: value, **(getattr(model, moved.group) or {})})


class DeprecatedAttribute:
    """The attribute of a model that a deprecated parameter was: reading or setting it warns and reads or writes the
    value where it lives now, ``model.<holder>.<key>`` or ``model.<holder>[key]``.

    :param holder: the model attribute that keeps the value (``planner``, ``demo_kwargs``)
    :param key: the value's attribute of ``holder``, or its key where ``holder`` is a dict
    :param in_dict: whether ``holder`` is a dict
    """

    def __init__(self, holder: str, key: str, in_dict: bool = False) -> None:
        self.holder = holder
        self.key = key
        self.in_dict = in_dict
        self.name = key

    @classmethod
    def of(cls, moved: MovedParameter) -> DeprecatedAttribute:
        """The attribute of a deprecated constructor parameter."""
        if moved.holder is None:
            return cls(moved.group, moved.key, in_dict=True)
        return cls(moved.holder, moved.key)

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def _warn(self, model: Any) -> None:
        where = f"{self.holder}[{self.key!r}]" if self.in_dict else f"{self.holder}.{self.key}"
        warn_deprecated(f"{type(model).__name__}.{self.name} is deprecated: use model.{where}")

    def __get__(self, model: Any, owner: type | None = None) -> Any:
        if model is None:
            return self
        self._warn(model)
        holder = getattr(model, self.holder)
        return holder[self.key] if self.in_dict else getattr(holder, self.key)

    def __set__(self, model: Any, value: Any) -> None:
        self._warn(model)
        holder = getattr(model, self.holder)
        if self.in_dict:
            holder[self.key] = value
        else:
            setattr(holder, self.key, value)
