"""Schemas of subjects (participants, known by a pseudonymous code)."""

from __future__ import annotations

from datetime import datetime

from pydantic import Field

from services.api.schemas.common import ApiRequest, PublicModel

CODE_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"


class SubjectCreate(ApiRequest):
    """A new subject: a pseudonymous code (never a name) and optional notes."""

    code: str = Field(pattern=CODE_PATTERN, description="Pseudonymous code, e.g. S01.")
    notes: str = Field("", max_length=10_000)


class SubjectUpdate(ApiRequest):
    """Changes to a subject; omitted fields stay."""

    code: str | None = Field(None, pattern=CODE_PATTERN)
    notes: str | None = Field(None, max_length=10_000)


class SubjectPublic(PublicModel):
    """A subject."""

    id: int
    code: str
    notes: str
    created_at: datetime
    updated_at: datetime
