"""Schemas of rigs (EEG set-ups)."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

from pydantic import Field

from services.api.schemas.common import ApiRequest, PublicModel

ChannelName = Annotated[str, Field(min_length=1, max_length=64)]
ChannelMap = Annotated[
    dict[ChannelName, ChannelName],
    Field(
        max_length=512,
        description="The amplifier's {device channel name: standard 10-20/10-10 name} (or "
        '\'Status\' for the trigger channel), e.g. BioSemi\'s {"A1": "Fp1"}; the EEG service '
        "checks it against the live stream when a session starts and names what does not fit.",
    ),
]


class RigCreate(ApiRequest):
    """A new rig (admin only)."""

    name: str = Field(min_length=1, max_length=100)
    location: str = Field("", max_length=200, description="Room or lab.")
    description: str = Field("", max_length=10_000)
    active: bool = True
    channel_map: ChannelMap | None = None


class RigUpdate(ApiRequest):
    """Changes to a rig; omitted fields stay."""

    name: str | None = Field(None, min_length=1, max_length=100)
    location: str | None = Field(None, max_length=200)
    description: str | None = Field(None, max_length=10_000)
    active: bool | None = None
    channel_map: ChannelMap | None = Field(
        None, description="The new channel map; {} removes it (standard names)."
    )


class RigPublic(PublicModel):
    """A rig."""

    id: int
    name: str
    location: str
    description: str
    active: bool
    channel_map: dict[str, str] | None
    created_at: datetime
    updated_at: datetime
