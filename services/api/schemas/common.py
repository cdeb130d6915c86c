"""Schemas shared by every resource: the page of a list route, a short message."""

from __future__ import annotations

from typing import Generic, TypeVar

from pydantic import BaseModel, ConfigDict, Field

ItemT = TypeVar("ItemT")

MAX_ROW_ID = 2**31 - 1
"""Largest integer id accepted (bigger ones cannot exist and would overflow the database)."""


class PublicModel(BaseModel):
    """A response built from a database row."""

    model_config = ConfigDict(from_attributes=True)


class Page(BaseModel, Generic[ItemT]):
    """One page of a list: ``items`` from ``offset``, and the ``total`` matching the filters."""

    items: list[ItemT]
    total: int = Field(ge=0)
    limit: int
    offset: int
