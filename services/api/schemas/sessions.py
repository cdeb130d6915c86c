"""Schemas of lab sessions."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import Field

from services.api.schemas.common import MAX_ROW_ID, ApiRequest, PublicModel, UtcDatetime

SessionKind = Literal["calibration", "test", "online", "rl"]
SessionStatus = Literal["scheduled", "running", "completed", "cancelled", "failed"]
MAX_DURATION_MINUTES = 24 * 60


class SessionCreate(ApiRequest):
    """A session to schedule; it may not overlap another of the same subject or rig."""

    subject_id: int = Field(ge=1, le=MAX_ROW_ID)
    kind: SessionKind
    scheduled_at: UtcDatetime = Field(description="Start, with a timezone (ISO 8601).")
    rig_id: int | None = Field(None, ge=1, le=MAX_ROW_ID)
    duration_minutes: int = Field(60, ge=1, le=MAX_DURATION_MINUTES)
    operator_id: int | None = Field(
        None, ge=1, le=MAX_ROW_ID, description="User running it (default: you)."
    )
    notes: str = Field("", max_length=10_000)
    allow_past: bool = Field(
        False,
        description="Schedule it even though it starts in the past (a session that has "
        "happened); without it such a start is refused (422 at scheduled_at).",
    )


class SessionUpdate(ApiRequest):
    """Reschedule or edit a session, or move it along scheduled -> running -> completed/failed.

    Cancel with ``POST /api/v1/sessions/{id}/cancel``.
    """

    kind: SessionKind | None = None
    scheduled_at: UtcDatetime | None = None
    rig_id: int | None = Field(None, ge=1, le=MAX_ROW_ID)
    duration_minutes: int | None = Field(None, ge=1, le=MAX_DURATION_MINUTES)
    operator_id: int | None = Field(None, ge=1, le=MAX_ROW_ID)
    notes: str | None = Field(None, max_length=10_000)
    status: Literal["running", "completed", "failed"] | None = None
    allow_past: bool = Field(
        False, description="Move it to a start in the past (else 422 at scheduled_at)."
    )


class SessionPublic(PublicModel):
    """A session."""

    id: int
    subject_id: int
    rig_id: int | None
    kind: SessionKind
    scheduled_at: datetime
    duration_minutes: int
    ends_at: datetime
    status: SessionStatus
    operator_id: int | None
    notes: str
    created_at: datetime
    updated_at: datetime
