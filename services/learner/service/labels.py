"""The labels of one HF session: records by marker id, and columns for fast checkpoints."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch


@dataclass(frozen=True)
class LabelRecord:
    """One label a session received."""

    marker_id: str
    observation: list[float]
    action: int
    correct: bool
    """The decoded feedback: True "correct", False "error"."""
    p_error: float | None
    oracle_correct: bool | None
    validation: bool
    """Held out for validation (never trained on)."""
    model_version: int
    """Model version after this label."""
    log_likelihood_ratio: float | None = None
    """The classifier's log P(epoch | error) / P(epoch | correct), when sent."""


class LabelTable:
    """Every label of a session in arrival order, looked up by marker id.

    Besides the records, the labels are kept as preallocated numpy columns, so
    :meth:`state_dict` costs a copy of a few arrays rather than pickling every record (the
    session is checkpointed every ``checkpoint_every`` journal entries).
    """

    def __init__(self, capacity: int, n_obs: int) -> None:
        self.records: list[LabelRecord] = []
        self._by_marker: dict[str, LabelRecord] = {}
        self._obs = np.zeros((capacity, n_obs), dtype=np.float32)
        self._action = np.zeros(capacity, dtype=np.int64)
        self._correct = np.zeros(capacity, dtype=np.bool_)
        self._p_error = np.full(capacity, np.nan, dtype=np.float64)
        self._oracle = np.full(capacity, -1, dtype=np.int8)  # -1 unknown, 0 error, 1 correct
        self._validation = np.zeros(capacity, dtype=np.bool_)
        self._version = np.zeros(capacity, dtype=np.int64)
        self._llr = np.full(capacity, np.nan, dtype=np.float64)
        self.n_known = 0
        """Labels with the oracle's truth."""
        self.n_agree = 0
        """Of those, labels whose feedback matches the truth."""

    def __len__(self) -> int:
        return len(self.records)

    def get(self, marker_id: str) -> LabelRecord | None:
        """The label of ``marker_id``, if received."""
        return self._by_marker.get(marker_id)

    def append(self, record: LabelRecord) -> None:
        """Add a label with a new marker id."""
        i = len(self.records)
        if i == len(self._action):
            raise OverflowError(f"the label table is full ({i} labels)")
        self._obs[i] = record.observation
        self._action[i] = record.action
        self._correct[i] = record.correct
        self._p_error[i] = math.nan if record.p_error is None else record.p_error
        self._oracle[i] = -1 if record.oracle_correct is None else int(record.oracle_correct)
        self._validation[i] = record.validation
        self._version[i] = record.model_version
        self._llr[i] = (
            math.nan if record.log_likelihood_ratio is None else record.log_likelihood_ratio
        )
        self.records.append(record)
        self._by_marker[record.marker_id] = record
        if record.oracle_correct is not None:
            self.n_known += 1
            self.n_agree += int(record.correct == record.oracle_correct)

    def state_dict(self) -> dict[str, Any]:
        """The labels as tensors (plus the marker ids), for ``torch.save``."""
        n = len(self.records)
        return {
            "marker_id": [r.marker_id for r in self.records],
            **{
                name: torch.from_numpy(column[:n].copy())
                for name, column in self._columns().items()
            },
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Replace the labels with those of :meth:`state_dict`."""
        n = len(state["marker_id"])
        self.__init__(len(self._action), self._obs.shape[1])  # type: ignore[misc]
        columns = {name: state[name].numpy() for name in self._columns() if name in state}
        # checkpoints from before soft labels hold no log-likelihood ratios
        columns.setdefault("log_likelihood_ratio", np.full(n, np.nan))
        for i in range(n):
            p_error = float(columns["p_error"][i])
            llr = float(columns["log_likelihood_ratio"][i])
            oracle = int(columns["oracle_correct"][i])
            self.append(
                LabelRecord(
                    marker_id=state["marker_id"][i],
                    observation=columns["observation"][i].tolist(),
                    action=int(columns["action"][i]),
                    correct=bool(columns["correct"][i]),
                    p_error=None if math.isnan(p_error) else p_error,
                    oracle_correct=None if oracle < 0 else bool(oracle),
                    validation=bool(columns["validation"][i]),
                    model_version=int(columns["model_version"][i]),
                    log_likelihood_ratio=None if math.isnan(llr) else llr,
                )
            )

    def _columns(self) -> dict[str, np.ndarray]:
        return {
            "observation": self._obs,
            "action": self._action,
            "correct": self._correct,
            "p_error": self._p_error,
            "oracle_correct": self._oracle,
            "validation": self._validation,
            "model_version": self._version,
            "log_likelihood_ratio": self._llr,
        }
