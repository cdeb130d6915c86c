"""The action marker that links a robot action to the EEG recorded while it was watched.

The simulator publishes one marker per executed action (on an LSL marker stream and in its
HTTP responses); the EEG service cuts the epoch [0, 0.8] s after ``timestamp``. Both sides
use this schema so that the link never depends on string formatting done twice.
"""

from __future__ import annotations

import json

from pydantic import BaseModel, ConfigDict, Field

from services.core.actions import TRIGGER_CORRECT, TRIGGER_ERROR, Action

MARKER_STREAM_NAME = "BrainNav-Markers"
MARKER_STREAM_TYPE = "Markers"


class ActionMarker(BaseModel):
    """One executed action, time-stamped on the LSL clock (seconds).

    Unknown fields and non-finite numbers are refused: a marker is also a request body
    (``POST /live/markers``) and is broadcast as JSON, which cannot carry NaN.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    session_id: str = Field(
        min_length=1, max_length=200, description="Sim session the action belongs to."
    )
    step: int = Field(ge=0, description="Step index within the session (0-based).")
    episode: int = Field(ge=0, description="Episode index within the session (0-based).")
    action: Action
    correct: bool | None = Field(
        None, description="Oracle verdict (True: optimal action), None when not evaluated."
    )
    timestamp: float = Field(description="LSL clock time (s) at which the action was shown.")

    @property
    def trigger(self) -> int:
        """Status code for recordings: 1 correct, 2 error (0 when not evaluated)."""
        if self.correct is None:
            return 0
        return TRIGGER_CORRECT if self.correct else TRIGGER_ERROR

    def to_lsl(self) -> str:
        """Serialise for a string LSL marker stream."""
        return self.model_dump_json()

    @classmethod
    def from_lsl(cls, text: str) -> ActionMarker:
        """Parse a marker string written by :meth:`to_lsl`.

        Raises ``ValueError`` if malformed: not JSON, or pydantic's ``ValidationError``
        (a ``ValueError``) naming the fields.
        """
        try:
            return cls.model_validate(json.loads(text))
        except (json.JSONDecodeError, TypeError) as exc:
            raise ValueError(f"not an action marker: {str(text)[:80]!r}") from exc
