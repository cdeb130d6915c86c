"""Schemas shared by every resource: the base of request bodies, the page of a list route,
the bounds of ids and timestamps."""

from __future__ import annotations

import re
from collections.abc import Iterator
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

from services.core.schemas import MAX_ROW_ID as MAX_ROW_ID  # the id bound of every request
from services.core.schemas import StrictRequest

ItemT = TypeVar("ItemT")

NO_NUL_PATTERN = r"^[^\x00]*$"
"""Text without NUL characters (PostgreSQL cannot store them): for query parameters."""
NUL_MESSAGE = "text may not contain NUL characters (\\u0000)"
_SURROGATE = re.compile(r"[\ud800-\udfff]")
EARLIEST = datetime(1900, 1, 1, tzinfo=UTC)
LATEST = datetime(9000, 1, 1, tzinfo=UTC)
"""Timestamps a request may carry: far from the ends of ``datetime``, so that adding a
duration or converting to UTC cannot overflow."""


SURROGATE_MESSAGE = (
    "text may not contain a lone surrogate (\\ud800-\\udfff): it is no Unicode character"
)


def _texts(value: Any) -> Iterator[str]:
    """Every text in ``value`` (text, or a list or mapping holding text, keys included)."""
    if isinstance(value, str):
        yield value
    elif isinstance(value, dict):
        for key, item in value.items():
            yield from _texts(key)
            yield from _texts(item)
    elif isinstance(value, list | tuple):
        for item in value:
            yield from _texts(item)


def unstorable_text(value: Any) -> str | None:
    """Why ``value`` (text, or a list or mapping holding text) cannot be stored and sent back,
    or None: a NUL character (PostgreSQL cannot store it) or a lone surrogate (JSON's
    ``"\\ud800"`` decodes to one; no UTF-8 can carry it, so the answer could not be sent)."""
    for text in _texts(value):
        if "\x00" in text:
            return NUL_MESSAGE
        if _SURROGATE.search(text):
            return SURROGATE_MESSAGE
    return None


class ApiRequest(StrictRequest):
    """A request body of the api: no unknown fields, no non-finite numbers and no text with
    NUL characters or lone surrogates (a 422 naming the field, never a database error or a
    500)."""

    @field_validator("*")
    @classmethod
    def _storable_text(cls, value: Any) -> Any:
        problem = unstorable_text(value)
        if problem is not None:
            raise ValueError(problem)
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
