"""Schemas of rigs (EEG set-ups)."""

from __future__ import annotations

from datetime import datetime

from pydantic import Field

from services.api.schemas.common import ApiRequest, PublicModel


class RigCreate(ApiRequest):
    """A new rig (admin only)."""

    name: str = Field(min_length=1, max_length=100)
    location: str = Field("", max_length=200, description="Room or lab.")
    description: str = Field("", max_length=10_000)
    active: bool = True


class RigUpdate(ApiRequest):
    """Changes to a rig; omitted fields stay."""

    name: str | None = Field(None, min_length=1, max_length=100)
    location: str | None = Field(None, max_length=200)
    description: str | None = Field(None, max_length=10_000)
    active: bool | None = None


class RigPublic(PublicModel):
    """A rig."""

    id: int
    name: str
    location: str
    description: str
    active: bool
    created_at: datetime
    updated_at: datetime
