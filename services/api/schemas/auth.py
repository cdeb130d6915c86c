"""Schemas of the login route and of API tokens."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import Field

from services.api.schemas.common import ApiRequest, PublicModel


class AccessToken(PublicModel):
    """An OAuth2 bearer access token (a short-lived JWT)."""

    access_token: str
    token_type: Literal["bearer"] = "bearer"
    expires_at: datetime


class ApiTokenCreate(ApiRequest):
    """A new API token for the signed-in user's scripts."""

    name: str = Field(min_length=1, max_length=100, description="What the token is for.")
    expires_in_days: int | None = Field(
        90, ge=1, le=3650, description="Lifetime in days; null for a token that never expires."
    )


class ApiTokenPublic(PublicModel):
    """An API token as listed (never the token itself)."""

    id: int
    user_id: int
    name: str
    token_prefix: str = Field(description="First characters of the token, to recognise it.")
    created_at: datetime
    expires_at: datetime | None
    revoked_at: datetime | None
    last_used_at: datetime | None


class ApiTokenCreated(ApiTokenPublic):
    """The new API token, including ``token``: shown this once, store it safely."""

    token: str
