"""Schemas of subjects (participants, known by a pseudonymous code)."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

from pydantic import Field

from services.api.schemas.common import ApiRequest, PublicModel, described_pattern

CODE_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"
SubjectCode = Annotated[
    str,
    *described_pattern(
        CODE_PATTERN,
        "a subject code: 1 to 64 letters, digits, '_', '.' or '-', starting with a letter "
        "or digit (e.g. S01)",
    ),
]


class SubjectCreate(ApiRequest):
    """A new subject: a pseudonymous code (never a name) and optional notes."""

    code: SubjectCode = Field(description="Pseudonymous code, e.g. S01.")
    notes: str = Field("", max_length=10_000)


class SubjectUpdate(ApiRequest):
    """Changes to a subject; omitted fields stay."""

    code: SubjectCode | None = None
    notes: str | None = Field(None, max_length=10_000)


class SubjectPublic(PublicModel):
    """A subject."""

    id: int
    code: str
    notes: str
    created_at: datetime
    updated_at: datetime
