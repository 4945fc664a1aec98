"""Loading a saved model and giving a model an env: SB3's ``save``, ``load`` and ``set_env`` with our algorithms' checks.

:class:`CheckedLoading` sits between each of our algorithms and its SB3 base class. It

* records the saving class's name in the zip's data (``saved_by``), and ``load`` refuses a file that another class
  saved with a ``ValueError`` naming that class (SB3 alone fails later, with a ``KeyError`` or a parameter mismatch);
* refuses an env whose time limit differs from the episode length the model's buffers were sized for
  (``max_episode_steps``), at ``load`` and at ``set_env``: trajectories would be cut into pieces without a word.
  ``load(path, env=env, max_episode_steps=N)`` rebuilds the model for the env's N-step episodes;
* rebuilds a model around its trained parameters (:meth:`CheckedLoading._rebuild_keeping_parameters`), with which
  ``set_env`` turns a model loaded without an env (predict-only buffers) into one that trains with its configured
  buffers, so SB3's ``model = X.load(path); model.set_env(env); model.learn(n, reset_num_timesteps=False)`` works.
"""

from __future__ import annotations

import io
import json
import pathlib
import zipfile
from typing import Any, TypeVar

import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.save_util import open_path, recursive_getattr, recursive_setattr
from stable_baselines3.common.type_aliases import GymEnv
from stable_baselines3.common.vec_env import VecEnv

from sb3_dipper.common.files import save_model_atomically

SelfCheckedLoading = TypeVar("SelfCheckedLoading", bound="CheckedLoading")


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


def _read_data_fields(file: io.BufferedIOBase) -> dict[str, Any]:
    try:
        with zipfile.ZipFile(file) as archive:
            if "data" not in archive.namelist():
                return {}
            fields = json.loads(archive.read("data").decode())
    except (zipfile.BadZipFile, json.JSONDecodeError):
        return {}
    return fields if isinstance(fields, dict) else {}


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
        """SB3's ``load``; refuses a file another algorithm saved, and an env whose time limit is not the model's
        episode length (pass ``max_episode_steps=`` the env's limit to rebuild the model for the env's episodes).
        """
        fields = saved_data_fields(path)
        saved_by = fields.get("saved_by")
        if saved_by is not None and saved_by != cls.__name__:
            raise ValueError(f"{path} was saved by {saved_by}; load it with {saved_by}.load, not {cls.__name__}.load")
        if env is not None:
            env = cls._wrap_env(env, int(fields.get("verbose", 0)))
            check_time_limit(
                env,
                kwargs.get("max_episode_steps", fields.get("max_episode_steps")),
                cls.__name__,
                f"rebuild it for the env's episodes with {cls.__name__}.load(path, env=env, max_episode_steps={{limit}})",
            )
        return super().load(path, env, device, custom_objects, print_system_info, force_reset, **kwargs)  # type: ignore[return-value]

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        """SB3's ``set_env``; refuses an env whose time limit is not the model's episode length."""
        env = self._wrap_env(env, self.verbose)
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
