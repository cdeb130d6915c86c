"""Schemas of users."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Literal

from pydantic import Field

from services.api.accounts import EMAIL_PATTERN, MIN_PASSWORD_CHARS
from services.api.schemas.common import ApiRequest, PublicModel, described_pattern

Role = Literal["admin", "staff", "viewer"]
Password = Annotated[str, Field(min_length=MIN_PASSWORD_CHARS, max_length=256)]


class UserCreate(ApiRequest):
    """A new account (admin only)."""

    email: Annotated[
        str,
        Field(max_length=320),
        *described_pattern(EMAIL_PATTERN, "an e-mail address like name@lab.org"),
    ]
    password: Password
    role: Role = "viewer"


class UserUpdate(ApiRequest):
    """Changes to an account (admin only); omitted fields stay."""

    role: Role | None = None
    active: bool | None = None
    password: Password | None = None


class PasswordChange(ApiRequest):
    """A user changing their own password."""

    current_password: str = Field(min_length=1, max_length=256)
    new_password: Password


class UserPublic(PublicModel):
    """An account as others see it (never the password hash)."""

    id: int
    email: str
    role: Role
    active: bool
    created_at: datetime
    last_login_at: datetime | None
