"""Schemas shared by every resource: the base of request bodies, the page of a list route,
the bounds of ids and timestamps."""

from __future__ import annotations

import re
from datetime import UTC, datetime
from typing import Annotated, Any, Generic, TypeVar

from pydantic import (
    AfterValidator,
    AwareDatetime,
    BaseModel,
    ConfigDict,
    Field,
    WithJsonSchema,
    field_validator,
)

from services.core.schemas import StrictRequest

ItemT = TypeVar("ItemT")

MAX_ROW_ID = 2**31 - 1
"""Largest integer id accepted (bigger ones cannot exist and would overflow the database)."""
NO_NUL_PATTERN = r"^[^\x00]*$"
"""Text without NUL characters (PostgreSQL cannot store them): for query parameters."""
NUL_MESSAGE = "text may not contain NUL characters (\\u0000)"
EARLIEST = datetime(1900, 1, 1, tzinfo=UTC)
LATEST = datetime(9000, 1, 1, tzinfo=UTC)
"""Timestamps a request may carry: far from the ends of ``datetime``, so that adding a
duration or converting to UTC cannot overflow."""


def has_nul(value: Any) -> bool:
    """True if ``value`` (text, or a list or mapping holding text) contains a NUL character."""
    if isinstance(value, str):
        return "\x00" in value
    if isinstance(value, dict):
        return any(has_nul(k) or has_nul(v) for k, v in value.items())
    if isinstance(value, list | tuple):
        return any(has_nul(v) for v in value)
    return False


class ApiRequest(StrictRequest):
    """A request body of the api: no unknown fields, no non-finite numbers and no text with
    NUL characters (a 422 naming the field, never a database error)."""

    @field_validator("*")
    @classmethod
    def _no_nul(cls, value: Any) -> Any:
        if has_nul(value):
            raise ValueError(NUL_MESSAGE)
        return value


def _utc_in_range(value: datetime) -> datetime:
    try:
        utc = value.astimezone(UTC)
    except OverflowError:
        utc = None
    if utc is None or not EARLIEST <= utc < LATEST:
        raise ValueError(
            f"must be between {EARLIEST:%Y-%m-%d} and {LATEST:%Y-%m-%d} (UTC), not {value}"
        )
    return utc


def described_pattern(pattern: str, words: str) -> Any:
    """A text field that must match ``pattern``, refused with ``words`` (what a person
    reads: "letters, digits, ...") rather than the regex; the schema still shows the
    pattern."""
    compiled = re.compile(pattern)

    def check(value: str) -> str:
        if not compiled.match(value):
            raise ValueError(f"{value!r} is not {words}"[:300])
        return value

    return [AfterValidator(check), WithJsonSchema({"type": "string", "pattern": pattern})]


UtcDatetime = Annotated[AwareDatetime, AfterValidator(_utc_in_range)]
"""A timestamp that must carry a timezone and lie between 1900 and 9000; kept in UTC."""


class PublicModel(BaseModel):
    """A response built from a database row."""

    model_config = ConfigDict(from_attributes=True)


class Page(BaseModel, Generic[ItemT]):
    """One page of a list: ``items`` from ``offset``, and the ``total`` matching the filters."""

    items: list[ItemT]
    total: int = Field(ge=0)
    limit: int
    offset: int
