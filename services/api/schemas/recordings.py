"""Schemas of recordings."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from services.api.schemas.common import PublicModel

ValidationStatus = Literal["pending", "valid", "invalid"]


class RecordingPublic(PublicModel):
    """A stored recording and what the EEG pipeline's validation found."""

    id: int
    session_id: int
    artifact_id: str
    filename: str
    sha256: str
    size_bytes: int
    synthetic: bool | None
    n_channels: int | None
    channels: list[str] | None
    sfreq: float | None
    duration_s: float | None
    validation_status: ValidationStatus
    validation_reason: str | None
    validated_at: datetime | None
    uploaded_by_id: int | None
    created_at: datetime
