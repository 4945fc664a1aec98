"""The label queue: a directory shared by the training process (which queues pairs) and the labelling page.

Layout of ``<directory>`` (every file written to a temporary name and renamed into place, read without pickle)::

    queue.json            what the pairs come from: ``env_id``, ``env_kwargs``, ``subgoal_space`` (or null)
    pairs/<id>.npz        one queued pair, written by training: ``observations/<key>``, ``actions``,
                          ``reached_actions``, ``next_achieved_goals`` ``(2, 1, T, ...)``, ``mask (2, 1, T)``
    labels.npz            people's answers, written by the page: ``pair_id (N,)`` int64, ``label (N,)`` float32 in
                          {0, 0.5, 1} or NaN for a skipped pair, ``time (N,)`` float64 (unix seconds)
    handed.npz            every pair handed to training, in order, written by training: ``pair_id``, ``label`` and
                          ``labeller`` (:data:`PERSON` or :data:`SCRIPT`), so who labelled each pair is on record
    images/<id>-<digest>-<side>.png
                          the page's picture of one side (left or right) of a pair, drawn on first view; the digest
                          is of the pair file's content (:meth:`LabelQueue.image_path`)

Each file has one writer, so neither side can lose the other's work, and a killed writer leaves the previous complete
file. The page serialises its answers with a lock file (``labels.lock``), so several tabs, or several pages, never
record two answers for one pair.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sb3_dipper.common.files import read_npz, save_npz, write_bytes_atomically
from sb3_dipper.common.preferences import TrajectoryPairs, pairs_from_arrays

# Who labelled a pair (the ``labeller`` column of handed.npz).
PERSON = 0
SCRIPT = 1
LABELLER_NAMES = {PERSON: "person", SCRIPT: "script"}

# Hex digits of a pair file's SHA-256 in the names of its pictures: 48 bits, so two pairs under one id never share one.
IMAGE_DIGEST_CHARS = 12

# The answers a person can give: 1 prefers the left (first) trajectory, 0 the right one, 0.5 neither, NaN skips.
ANSWERS = {"left": 1.0, "right": 0.0, "equal": 0.5, "skip": float("nan")}


@dataclass(frozen=True)
class Answers:
    """The answers recorded in ``labels.npz`` (one per pair id; NaN labels are skipped pairs)."""

    pair_ids: np.ndarray
    labels: np.ndarray
    times: np.ndarray

    @classmethod
    def empty(cls) -> Answers:
        return cls(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.float32), np.zeros(0, dtype=np.float64))

    def as_dict(self) -> dict[int, float]:
        return dict(zip(self.pair_ids.tolist(), self.labels.tolist(), strict=True))


class LabelQueue:
    """The files of one label queue directory (see the module docstring for the layout).

    :param directory: the queue directory (created by the training side; the page only reads what is there)
    """

    def __init__(self, directory: str | os.PathLike) -> None:
        self.directory = Path(directory)
        self.pairs_dir = self.directory / "pairs"
        self.images_dir = self.directory / "images"
        self.labels_path = self.directory / "labels.npz"
        self.handed_path = self.directory / "handed.npz"
        self.info_path = self.directory / "queue.json"
        self._answers_stamp: tuple[int, int] | None = None
        self._answers = Answers.empty()

    # ------------------------------------------------------------------------------------------------ queue info

    def write_info(self, info: dict[str, Any]) -> None:
        write_bytes_atomically(self.info_path, json.dumps(info, indent=2, sort_keys=True).encode())

    def read_info(self) -> dict[str, Any]:
        if not self.info_path.exists():
            return {}
        try:
            info = json.loads(self.info_path.read_text())
        except json.JSONDecodeError as error:
            raise ValueError(f"Malformed queue file {self.info_path}: {error}. Delete it to have it rewritten.") from error
        if not isinstance(info, dict):
            raise ValueError(f"Malformed queue file {self.info_path}: expected a JSON object")
        return info

    # ------------------------------------------------------------------------------------------------ pairs

    def pair_path(self, pair_id: int) -> Path:
        return self.pairs_dir / f"{pair_id:08d}.npz"

    def write_pair(self, pair_id: int, pairs: TrajectoryPairs, index: int) -> None:
        """Queue pair ``index`` of ``pairs`` under ``pair_id``."""
        one = pairs.select(np.array([index]))
        arrays = {f"observations/{key}": value for key, value in one.observations.items()}
        arrays.update(
            actions=one.actions,
            reached_actions=one.reached_actions,
            next_achieved_goals=one.next_achieved_goals,
            mask=one.mask,
        )
        save_npz(self.pair_path(pair_id), arrays)

    def read_pair(self, pair_id: int, label: float = float("nan")) -> TrajectoryPairs:
        """The queued pair ``pair_id`` (a batch of one) with ``label``, checked as a preference file's pairs are."""
        path = self.pair_path(pair_id)
        arrays = read_npz(path, "queued pair", "Was the label queue directory edited by hand?")
        missing = [key for key in ("actions", "reached_actions", "next_achieved_goals", "mask") if key not in arrays]
        if missing or not any(key.startswith("observations/") for key in arrays):
            raise ValueError(f"Malformed queued pair {path}: missing {missing or 'observations'}")
        # The label is checked with labels.npz (answers); a placeholder stands in for the pair's checks.
        pair = pairs_from_arrays({**arrays, "labels": np.zeros(1, np.float32)}, f"queued pair {path}")
        pair.labels = np.array([label], dtype=np.float32)
        return pair

    def image_path(self, pair_id: int, side: str) -> Path:
        """Where the page keeps its picture of one side (``"left"`` or ``"right"``) of the queued pair ``pair_id``.

        The name holds a digest of the pair file as well as its id: ids start again from 0 when someone clears
        ``pairs/``, ``labels.npz`` and ``handed.npz`` by hand but leaves ``images/``, and a picture must never be shown
        for another pair. Counting ``images/`` among the ids in use would cover that case only, not a pair file
        replaced by hand; the digest covers every way a pair can change, for one read of a file of a few kilobytes.
        """
        digest = hashlib.sha256(self.pair_path(pair_id).read_bytes()).hexdigest()[:IMAGE_DIGEST_CHARS]
        return self.images_dir / f"{pair_id:08d}-{digest}-{side}.png"

    def queued_ids(self) -> list[int]:
        """Every pair id with a file in ``pairs/``, ascending."""
        if not self.pairs_dir.is_dir():
            return []
        return sorted(int(path.stem) for path in self.pairs_dir.glob("*.npz") if path.stem.isdigit())

    def waiting_ids(self) -> list[int]:
        """Queued pairs without an answer, oldest first."""
        answered = set(self.answers().pair_ids.tolist())
        return [pair_id for pair_id in self.queued_ids() if pair_id not in answered]

    # ------------------------------------------------------------------------------------------------ answers

    def answers(self) -> Answers:
        """The answers in ``labels.npz``, reread only when the file changed."""
        try:
            stat = self.labels_path.stat()
        except FileNotFoundError:
            self._answers_stamp, self._answers = None, Answers.empty()
            return self._answers
        stamp = (stat.st_mtime_ns, stat.st_ino)
        if stamp != self._answers_stamp:
            arrays = read_npz(self.labels_path, "label file", "Restore it from a backup, or delete it to start over.")
            for key in ("pair_id", "label", "time"):
                if key not in arrays or arrays[key].ndim != 1 or len(arrays[key]) != len(arrays["pair_id"]):
                    raise ValueError(f"Malformed label file {self.labels_path}: {key} must be a vector, one per pair_id")
            labels = arrays["label"]
            # The values PreferenceDataset.load accepts, and NaN for a skipped pair.
            if labels.dtype.kind != "f" or not np.all(np.isnan(labels) | np.isin(labels, (0.0, 0.5, 1.0))):
                raise ValueError(
                    f"Malformed label file {self.labels_path}: label must hold 0, 0.5, 1 or NaN (skipped), got "
                    f"{np.unique(labels).tolist()}. Correct the hand-edited labels, or restore the file from a backup."
                )
            if arrays["pair_id"].dtype.kind not in "iu":
                raise ValueError(f"Malformed label file {self.labels_path}: pair_id must hold integers")
            self._answers = Answers(
                arrays["pair_id"].astype(np.int64), arrays["label"].astype(np.float32), arrays["time"].astype(np.float64)
            )
            self._answers_stamp = stamp
        return self._answers

    @contextmanager
    def _answers_lock(self) -> Iterator[None]:
        self.directory.mkdir(parents=True, exist_ok=True)
        with open(self.directory / "labels.lock", "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(lock, fcntl.LOCK_UN)

    def record_answer(self, pair_id: int, label: float, replace_skip: bool = False) -> bool:
        """Record one answer for a queued pair; False (nothing written) if the pair has an answer already.

        :param pair_id: the pair
        :param label: 1, 0, 0.5, or NaN to skip it
        :param replace_skip: let a real label replace an earlier skip (the page's ``--show-skipped``)
        """
        if not (np.isnan(label) or label in (0.0, 0.5, 1.0)):
            raise ValueError(f"A label is 0, 0.5, 1 or NaN (skip), got {label}")
        with self._answers_lock():
            self._answers_stamp = None  # another process may have written since: read afresh under the lock
            answers = self.answers()
            known = answers.pair_ids == pair_id
            if known.any():
                if not (replace_skip and np.isnan(answers.labels[known]).all() and not np.isnan(label)):
                    return False
                keep = ~known
                answers = Answers(answers.pair_ids[keep], answers.labels[keep], answers.times[keep])
            save_npz(
                self.labels_path,
                {
                    "pair_id": np.append(answers.pair_ids, np.int64(pair_id)),
                    "label": np.append(answers.labels, np.float32(label)),
                    "time": np.append(answers.times, time.time()),
                },
            )
            self._answers_stamp = None
        return True

    # ------------------------------------------------------------------------------------------------ hand-over record

    def read_handed(self) -> dict[str, np.ndarray]:
        if not self.handed_path.exists():
            return {"pair_id": np.zeros(0, np.int64), "label": np.zeros(0, np.float32), "labeller": np.zeros(0, np.int8)}
        return read_npz(
            self.handed_path,
            "hand-over record",
            "Delete it: training writes it again.",
            required=("pair_id", "label", "labeller"),
        )

    def append_handed(self, pair_ids: np.ndarray, labels: np.ndarray, labeller: np.ndarray) -> None:
        record = self.read_handed()
        save_npz(
            self.handed_path,
            {
                "pair_id": np.concatenate([record["pair_id"], pair_ids.astype(np.int64)]),
                "label": np.concatenate([record["label"], labels.astype(np.float32)]),
                "labeller": np.concatenate([record["labeller"], labeller.astype(np.int8)]),
            },
        )

    def next_free_id(self) -> int:
        """One more than every pair id the directory knows (queued, answered or handed over)."""
        known = [*self.queued_ids(), *self.answers().pair_ids.tolist(), *self.read_handed()["pair_id"].tolist()]
        return max(known, default=-1) + 1
