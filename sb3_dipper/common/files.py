"""Files the library writes and reads: each written whole or not at all, each read with errors that name it.

Writing: a file goes to a temporary name in its own folder and is renamed into place (``os.replace`` is atomic), so a
reader, or a run killed mid-write (a checkpoint, the cached default demonstration), finds the previous complete file or
the new complete one under the final name, never a truncated one; a kill can only leave a ``.<name>.<pid>.<hex>.tmp``
file behind.

Reading: our npz files are read without pickle, and a missing, truncated or foreign file raises an error that names
it and says what to do. Replay buffers stay SB3's pickles (the format of its ``save_replay_buffer``); they are read
whole and checked against the model before they replace anything, so a failed load leaves the model as it was.
"""

from __future__ import annotations

import io
import os
import secrets
import zipfile
import zlib
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.save_util import load_from_pkl, save_to_pkl
from stable_baselines3.her.her_replay_buffer import HerReplayBuffer

# How a zip archive (so an npz file) begins: a local file header, or the end record of an empty archive.
ZIP_SIGNATURES = (b"PK\x03\x04", b"PK\x05\x06")

PathLike = str | os.PathLike


def write_atomically(path: PathLike, write: Callable[[io.BufferedWriter], object]) -> Path:
    """Run ``write(file)`` on a temporary file beside ``path``, then rename it to ``path``; return ``path``.

    On any error (or interruption) the temporary file is removed and ``path`` keeps its previous content.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    try:
        with open(temporary, "xb") as file:
            write(file)
            file.flush()
            # Rename only what is on disk, so a crash of the machine cannot leave an empty file under the final name.
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    return path


def write_bytes_atomically(path: PathLike, data: bytes) -> Path:
    """``data`` as the whole content of ``path``, written as :func:`write_atomically` writes."""
    return write_atomically(path, lambda file: file.write(data))


def npz_path(path: PathLike) -> Path:
    """Where ``np.savez(path)`` writes: numpy appends ``.npz`` to a name that does not end with it."""
    path = Path(path)
    return path if path.name.endswith(".npz") else path.with_name(f"{path.name}.npz")


def save_npz(path: PathLike, arrays: dict[str, np.ndarray]) -> Path:
    """Write ``arrays`` to a compressed npz file at ``path`` (``.npz`` appended as numpy does), atomically."""
    return write_atomically(npz_path(path), lambda file: np.savez_compressed(file, **arrays))  # type: ignore[arg-type]


def read_npz(path: PathLike, what: str, fix: str = "", required: Iterable[str] = ()) -> dict[str, np.ndarray]:
    """Every array of the npz file at ``path``, read without pickle.

    :param path: the file
    :param what: what the file is, for messages (``"demonstration file"``)
    :param fix: what the user can do about a bad file, appended to every message
    :param required: the arrays the file must hold (one missing is a malformed file, not a bare ``KeyError``)
    :raises FileNotFoundError: no file at ``path``
    :raises ValueError: anything else: not an npz archive, truncated, or holding pickled objects
    """
    path = Path(path)
    advice = f" {fix}" if fix else ""
    try:
        with open(path, "rb") as file:
            signature = file.read(4)
    except FileNotFoundError as error:
        raise FileNotFoundError(f"No {what} at {path}.{advice}") from error
    except IsADirectoryError as error:
        raise ValueError(f"Malformed {what} {path}: it is a directory, not an npz file.{advice}") from error
    if signature not in ZIP_SIGNATURES:
        found = "it is empty" if not signature else f"it starts with {signature!r}"
        raise ValueError(f"Malformed {what} {path}: not an npz archive ({found}).{advice}")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except (zipfile.BadZipFile, EOFError, zlib.error, OSError) as error:
        raise ValueError(
            f"Malformed {what} {path}: not a complete npz archive ({error}); was its writing interrupted?{advice}"
        ) from error
    except ValueError as error:
        if "allow_pickle" in str(error):
            # numpy's own message advises allow_pickle=True, which these files never need.
            raise ValueError(
                f"Malformed {what} {path}: it holds pickled Python objects, which are never loaded; "
                f"npz files here hold numeric arrays only.{advice}"
            ) from error
        raise ValueError(f"Malformed {what} {path}: {error}.{advice}") from error
    not_arrays = [key for key, value in arrays.items() if not isinstance(value, np.ndarray)]
    if not_arrays:
        raise ValueError(f"Malformed {what} {path}: members {not_arrays} are not .npy arrays.{advice}")
    missing = [key for key in required if key not in arrays]
    if missing:
        raise ValueError(f"Malformed {what} {path}: missing {missing}.{advice}")
    return arrays


def replay_buffer_path(path: Any, owner: str, reading: bool) -> Path:
    """The file SB3's ``save_replay_buffer(path)`` / ``load_replay_buffer(path)`` would use (``.pkl`` added if needed).

    Streams are refused: the data kept beside the replay buffer needs a file name to sit beside.

    :param path: what the user passed
    :param owner: the method, for the message (``"DIPPER.save_replay_buffer"``)
    :param reading: whether the file is read (SB3 then tries ``path`` first, ``path.pkl`` second)
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(
            f"{owner} needs a file path (str or pathlib.Path), not a {type(path).__name__}: it also writes data of "
            "its own to files named after the path (replay_buffer.pkl -> replay_buffer.high.npz, ...), which a stream "
            "cannot name. Pass a path such as 'replay_buffer.pkl'."
        )
    path = Path(path)
    if reading:
        with_suffix = Path(f"{path}.pkl")
        return with_suffix if not path.exists() and with_suffix.exists() else path
    return Path(f"{path}.pkl") if path.suffix == "" else path


def save_replay_buffer_file(path: PathLike, buffer: ReplayBuffer | None) -> None:
    """SB3's pickle of ``buffer`` (what ``save_replay_buffer`` writes), written atomically."""
    assert buffer is not None, "The replay buffer is not defined"
    write_atomically(path, lambda file: save_to_pkl(file, buffer))  # type: ignore[arg-type]


def read_replay_buffer(
    path: PathLike | io.BufferedIOBase, learner: OffPolicyAlgorithm, truncate_last_traj: bool
) -> ReplayBuffer:
    """The replay buffer SB3 pickled at ``path`` (a file or a stream), checked against ``learner``, not installed.

    It is what ``learner.load_replay_buffer(path)`` would install (HER buffers get the learner's env and, with
    ``truncate_last_traj``, a truncated last episode); assign it to ``learner.replay_buffer`` to install it.
    """
    fix = "Load the replay buffer of another (complete) checkpoint, or resume without one (load the model only)."
    try:
        buffer = load_from_pkl(path if isinstance(path, io.BufferedIOBase) else Path(path))
    except FileNotFoundError as error:
        raise FileNotFoundError(f"No replay buffer at {path}. Pass the path save_replay_buffer wrote.") from error
    except Exception as error:  # unpickling fails in many ways (EOFError, UnpicklingError, ImportError, ...)
        raise ValueError(
            f"Unreadable replay buffer {path} ({type(error).__name__}: {error}); was its writing interrupted? {fix}"
        ) from error
    if not isinstance(buffer, ReplayBuffer):
        raise ValueError(f"{path} holds a {type(buffer).__name__}, not an SB3 replay buffer. {fix}")
    expected = learner.replay_buffer
    if expected is not None:
        problem = _buffer_mismatch(buffer, expected)
        if problem:
            raise ValueError(f"The replay buffer {path} does not fit this model: {problem}. Was it saved by another model?")
    if isinstance(buffer, HerReplayBuffer):
        if learner.env is None:
            raise ValueError(f"{path} is a HerReplayBuffer, which needs the env: load the model with env=... first")
        buffer.set_env(learner.env)  # type: ignore[arg-type]
        if truncate_last_traj:
            buffer.truncate_last_trajectory()
    buffer.device = learner.device
    return buffer


def _buffer_mismatch(buffer: ReplayBuffer, expected: ReplayBuffer) -> str:
    """What makes ``buffer`` unfit to replace ``expected`` (empty if nothing)."""
    if not isinstance(buffer, type(expected)):
        return f"it is a {type(buffer).__name__}, the model uses a {type(expected).__name__}"
    if buffer.n_envs != expected.n_envs:
        return f"it was filled by {buffer.n_envs} envs, the model has {expected.n_envs}"
    found, wanted = space_shapes(buffer.observation_space), space_shapes(expected.observation_space)
    if found != wanted:
        return f"its observations have shapes {found}, the model's have {wanted}"
    if buffer.action_space.shape != expected.action_space.shape:
        return f"its actions have shape {buffer.action_space.shape}, the model's have {expected.action_space.shape}"
    return ""


def space_shapes(space: spaces.Space) -> dict[str, tuple[int, ...]] | tuple[int, ...] | None:
    """The shape of a Box, or the shape of each key of a Dict."""
    if isinstance(space, spaces.Dict):
        return {key: subspace.shape for key, subspace in space.spaces.items()}  # type: ignore[misc]
    return space.shape


def model_zip_path(path: PathLike) -> Path:
    """Where SB3's ``save(path)`` writes the model: ``.zip`` is added to a name without a suffix."""
    path = Path(path)
    return Path(f"{path}.zip") if path.suffix == "" else path


def save_model_atomically(
    save: Callable[[Any, Iterable[str] | None, Iterable[str] | None], None],
    path: Any,
    exclude: Iterable[str] | None,
    include: Iterable[str] | None,
) -> None:
    """Run SB3's ``save(path, exclude, include)``; to a path, through a temporary file renamed into place."""
    if isinstance(path, (str, os.PathLike)):
        write_atomically(model_zip_path(path), lambda file: save(file, exclude, include))
    else:
        save(path, exclude, include)
