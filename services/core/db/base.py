"""Declarative base of every platform table, with named constraints and UTC timestamps."""

from __future__ import annotations

import uuid
from collections.abc import Callable
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import DateTime, MetaData
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase
from sqlalchemy.types import TypeDecorator

NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}
"""Every constraint gets a stable name, so migrations can alter it on SQLite and PostgreSQL."""


def utcnow() -> datetime:
    """The current time, timezone-aware UTC."""
    return datetime.now(UTC)


def new_id() -> str:
    """A new 32-character hex id (uuid4) for rows that workers on other hosts create too."""
    return uuid.uuid4().hex


_combine = datetime.combine
"""``datetime.combine(day, time, tzinfo)``: a third of ``replace(tzinfo=...)``'s time, which
matters where every timestamp of a page of rows goes through it."""


class UtcDateTime(TypeDecorator[datetime]):
    """A timestamp stored in UTC and always read back timezone-aware (SQLite included).

    Naive values are refused when written: a naive time is ambiguous. PostgreSQL sessions
    run in UTC (:func:`services.core.db.session.make_engine`), so what psycopg reads is
    already UTC and passes through; SQLite's text is parsed and marked UTC.
    """

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("naive datetime: give timestamps with a timezone (UTC)")
        if value.tzinfo is not UTC:
            value = value.astimezone(UTC)
        return _combine(value, value.time()) if dialect.name == "sqlite" else value

    def result_processor(self, dialect: Dialect, coltype: Any) -> Callable[[Any], datetime | None]:
        """One function per read value (rather than the impl's processor, then a
        ``process_result_value``): the impl's parsing of the database's value (SQLite:
        ISO text), then UTC."""
        parse = self.impl_instance.result_processor(dialect, coltype)
        if parse is None:  # a driver's datetime (psycopg: in the session's zone, UTC)

            def read_value(value: datetime | None) -> datetime | None:
                if value is None or value.tzinfo is UTC:
                    return value
                if value.tzinfo is None:
                    return _combine(value, value.time(), UTC)
                return value.astimezone(UTC)

            return read_value

        def read_text(value: Any) -> datetime | None:
            if value is None:
                return None
            parsed: datetime = parse(value)
            if parsed.tzinfo is None:
                return _combine(parsed, parsed.time(), UTC)
            return parsed.astimezone(UTC)

        return read_text


class Base(DeclarativeBase):
    """Base class of the platform's models."""

    metadata = MetaData(naming_convention=NAMING_CONVENTION)
