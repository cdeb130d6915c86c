"""Small helpers the routes share: fetch-or-404, pagination, partial updates, and the JSON
of a page written straight from its rows (the hot list routes)."""

from __future__ import annotations

import json
import math
import types
import typing
from collections.abc import Callable, Collection, Sequence
from datetime import UTC, datetime
from json.encoder import encode_basestring
from typing import Any, Literal, TypeVar

import pydantic_core
from pydantic import BaseModel
from sqlalchemy import (
    JSON,
    ColumnElement,
    Select,
    Table,
    Text,
    bindparam,
    cast,
    func,
    select,
)
from sqlalchemy.engine import Connection
from sqlalchemy.ext.compiler import compiles
from sqlalchemy.orm import Session
from sqlalchemy.sql.compiler import SQLCompiler
from sqlalchemy.sql.functions import FunctionElement

from services.api.deps import PageParams
from services.core.db.base import UtcDateTime
from services.core.db.models import Job
from services.core.errors import ConflictError, NotFoundError

RowT = TypeVar("RowT")
TOTAL_COLUMN = "total_matching"
"""Name of the count column :func:`paginate` adds to a list query."""


def get_row(db: Session, model: type[RowT], row_id: object) -> RowT | None:
    """The row of ``model`` with primary key ``row_id``, or None (also for a text id no row
    can have: one with a NUL character, which PostgreSQL cannot even compare)."""
    return None if isinstance(row_id, str) and "\x00" in row_id else db.get(model, row_id)


def get_or_404(db: Session, model: type[RowT], row_id: object, field: str) -> RowT:
    """The row of ``model`` with primary key ``row_id``; 404 naming ``field`` otherwise."""
    row = get_row(db, model, row_id)
    if row is None:
        name = getattr(model, "__tablename__", model.__name__).rstrip("s").replace("_", " ")
        raise NotFoundError(f"no {name} with id {row_id}", field=field)
    return row


MIN_ID_PREFIX = 6
"""The fewest leading characters of a text id (a job's, an artifact's: 32 hex digits) that
:func:`get_by_id_or_prefix` takes for the whole id."""
NAMED_CANDIDATES = 5
"""How many matching ids a 409 for an ambiguous prefix names."""
HEX_DIGITS = frozenset("0123456789abcdef")


def get_by_id_or_prefix(db: Session, model: type[RowT], row_id: str, field: str) -> RowT:
    """The row of ``model`` (a text primary key of hex digits) whose id is ``row_id``, or
    starts with it: any unique prefix of at least :data:`MIN_ID_PREFIX` characters, as the
    dashboard shows ids and people type them. 404 naming ``field`` when none matches, 409
    naming the candidates when several do."""
    row = get_row(db, model, row_id)
    if row is not None:
        return row
    name = getattr(model, "__tablename__", model.__name__).rstrip("s").replace("_", " ")
    prefix = row_id.lower()
    if len(prefix) < MIN_ID_PREFIX or not set(prefix) <= HEX_DIGITS:
        short = prefix and len(prefix) < MIN_ID_PREFIX and set(prefix) <= HEX_DIGITS
        hint = f" (give at least {MIN_ID_PREFIX} characters of it)" if short else ""
        raise NotFoundError(f"no {name} with id {row_id}{hint}", field=field)
    key = model.id  # type: ignore[attr-defined]
    ids = list(
        db.scalars(
            select(key).where(key.startswith(prefix)).order_by(key).limit(NAMED_CANDIDATES + 1)
        )
    )
    if not ids:
        raise NotFoundError(f"no {name} with an id starting {row_id}", field=field)
    if len(ids) > 1:
        named = ", ".join(ids[:NAMED_CANDIDATES])
        more = " and more" if len(ids) > NAMED_CANDIDATES else ""
        raise ConflictError(
            f"{row_id} starts the ids of several {name}s: {named}{more}; give more characters",
            field=field,
        )
    found = db.get(model, ids[0])
    assert found is not None
    return found


ACTIVE_JOB_STATUSES = ("queued", "running")


def busy_job(
    db: Session,
    *,
    subject_id: int | None = None,
    session_ids: Collection[int] = (),
    recording_ids: Collection[int] = (),
) -> Job | None:
    """A queued or running job working on the subject, its sessions or its recordings (a live
    session, a BIDS export, a replay, a calibration), which deleting them would break."""
    active = db.scalars(
        select(Job).where(Job.status.in_(ACTIVE_JOB_STATUSES))
    )  # few jobs are active at once; those of other kinds name none of these ids
    for job in active:
        config = job.config or {}
        if (
            (subject_id is not None and config.get("subject_id") == subject_id)
            or config.get("session_id") in session_ids
            or config.get("recording_id") in recording_ids
        ):
            return job
    return None


def page_rows(
    db: Session | Connection, query: Select[Any], page: PageParams
) -> tuple[Sequence[Any], int]:
    """The rows of ``query`` (already filtered and ordered) on ``page``, and the total
    matching. The total comes in the same query, as a last column counted once; only a page
    past the end needs a second query for it."""
    count = select(func.count()).select_from(query.order_by(None).subquery()).correlate(None)
    counted = query.add_columns(count.scalar_subquery().label(TOTAL_COLUMN))
    rows = db.execute(counted.limit(page.limit).offset(page.offset)).all()
    if rows:
        total = rows[0][-1]
    elif page.offset == 0:
        total = 0
    else:  # past the end: count on its own
        total = db.scalar(count) or 0
    return rows, total


def paginate(db: Session, query: Select[Any], page: PageParams) -> dict[str, Any]:
    """``{"items", "total", "limit", "offset"}`` of ``query`` (already filtered and ordered).

    A query of one entity gives its rows as ``items``; a query of several columns gives
    one dict per row (cheaper: no ORM objects, only what the response returns).
    """
    rows, total = page_rows(db, query, page)
    if len(query.column_descriptions) == 1:
        items: list[Any] = [row[0] for row in rows]
    else:
        names = [column["name"] for column in query.column_descriptions]
        items = [dict(zip(names, row[:-1], strict=True)) for row in rows]
    return {"items": items, "total": total, "limit": page.limit, "offset": page.offset}


def apply_update(row: object, update: BaseModel) -> dict[str, Any]:
    """Set the fields given (not null) in ``update`` on ``row``; the changes made."""
    changes = update.model_dump(exclude_unset=True, exclude_none=True)
    for key, value in changes.items():
        setattr(row, key, value)
    return changes


def _json_float(value: float) -> str:
    # pydantic writes non-finite floats as null
    return repr(float(value)) if math.isfinite(value) else "null"


def _json_bool(value: bool) -> str:
    return "true" if value else "false"


def _json_stored(value: str) -> str:
    """A JSON column's stored text, as is. Only SQLite can hold the non-standard NaN or
    Infinity (PostgreSQL's json type refuses them): those values are decoded and written as
    pydantic writes them (null)."""
    if "NaN" in value or "Infinity" in value:
        return pydantic_core.to_json(json.loads(value), inf_nan_mode="null").decode()
    return value


class utc_text(FunctionElement[str]):  # noqa: N801 (a SQL function)
    """A UTC timestamp column as the text ``2026-01-02 03:04:05.123456``: SQLite's stored
    text itself, PostgreSQL's ``to_char`` of it (cheaper than a datetime to format)."""

    type = Text()
    inherit_cache = True


@compiles(utc_text)
def _utc_text_stored(element: utc_text, compiler: SQLCompiler, **kw: Any) -> str:
    return compiler.process(element.clauses, **kw)


@compiles(utc_text, "postgresql")
def _utc_text_postgresql(element: utc_text, compiler: SQLCompiler, **kw: Any) -> str:
    column = compiler.process(element.clauses, **kw)
    return f"to_char({column} AT TIME ZONE 'UTC', 'YYYY-MM-DD HH24:MI:SS.US')"


def _json_timestamp(value: str | datetime) -> str:
    """A UTC timestamp as pydantic writes it (``2026-01-02T03:04:05.123456Z``, no fraction
    when it is zero), from :class:`utc_text`'s text; another text form or a datetime is
    parsed (a SQLite row written by other means)."""
    if isinstance(value, str):
        if len(value) == 26 and value[10] == " " and value[19] == ".":
            fraction = "" if value.endswith(".000000") else value[19:]
            return f'"{value[:10]}T{value[11:19]}{fraction}Z"'
        value = datetime.fromisoformat(value)  # another stored form: parse it
    if value.tzinfo is None:  # stored in UTC (UtcDateTime)
        value = value.replace(tzinfo=UTC)
    elif value.utcoffset():
        value = value.astimezone(UTC)
    return f'"{value.isoformat()[:-6]}Z"'


def _writer(name: str, annotation: Any, column: ColumnElement[Any]) -> Callable[[Any], str]:
    """The JSON writer of a non-null value of field ``name`` (typed ``annotation``, read
    from ``column``); TypeError for a type written here unlike pydantic would."""
    if isinstance(column.type, JSON):
        return _json_stored
    if isinstance(column.type, UtcDateTime):
        return _json_timestamp
    if typing.get_origin(annotation) is Literal:
        annotation = type(typing.get_args(annotation)[0])
    writers: dict[Any, Callable[[Any], str]] = {
        str: encode_basestring,
        bool: _json_bool,
        int: str,
        float: _json_float,
    }
    if annotation not in writers:
        raise TypeError(f"no JSON writer for field {name}: {annotation!r} ({column.type!r})")
    return writers[annotation]


def _not_none(annotation: Any) -> Any:
    """The type of a field without ``None`` (``int`` of ``int | None``)."""
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        args = [arg for arg in typing.get_args(annotation) if arg is not type(None)]
        if len(args) == 1:
            return args[0]
    return annotation


class PageQuery:
    """A list query built once, with its filters, limit and offset as parameters, and run
    for any page: building a query with its count costs more CPU than running it."""

    def __init__(self, query: Select[Any]) -> None:
        self.count: Select[Any] = (
            select(func.count()).select_from(query.order_by(None).subquery()).correlate(None)
        )
        """The number of rows ``query`` matches."""
        self.page: Select[Any] = (
            query.add_columns(self.count.scalar_subquery().label(TOTAL_COLUMN))
            .limit(bindparam("page_limit"))
            .offset(bindparam("page_offset"))
        )
        """One page of ``query``, each row ending with the total matching."""

    def rows(
        self, db: Connection, page: PageParams, params: dict[str, Any]
    ) -> tuple[Sequence[Any], int]:
        """The rows on ``page`` (without the total) and the total matching, for the
        filters' values ``params``. Only a page past the end needs a second query."""
        rows = db.execute(
            self.page, {**params, "page_limit": page.limit, "page_offset": page.offset}
        ).all()
        if rows:
            total = rows[0][-1]
        elif page.offset == 0:
            total = 0
        else:  # past the end: count on its own
            total = db.scalar(self.count, params) or 0
        return rows, total


class JsonPage:
    """The JSON of ``Page[model]`` written straight from the rows of ``table``: the same
    JSON document the pydantic model gives for those rows (a test holds them equal), at a
    fraction of the CPU. Only the model's columns are selected, as plain rows; JSON columns
    come as their stored text (cast to text in SQL) and are passed through; timestamps are
    formatted from their UTC text (:class:`utc_text`); the rows are not validated
    again (they are what the database's types and constraints allow). The values are
    written a column at a time (``map`` over a column's values), then joined into objects
    with one ``%`` template."""

    def __init__(self, model: type[BaseModel], table: Table) -> None:
        self.model = model
        columns: list[ColumnElement[Any]] = []
        self._writers: list[tuple[Callable[[Any], str], bool]] = []
        keys = []
        for name, field in model.model_fields.items():
            column = table.c[name]
            write = _writer(name, _not_none(field.annotation), column)
            if write is _json_stored:
                columns.append(cast(column, Text).label(name))
            elif write is _json_timestamp:
                columns.append(utc_text(column).label(name))
            else:
                columns.append(column)
            self._writers.append((write, bool(column.nullable)))
            keys.append(encode_basestring(name).replace("%", "%%") + ":%s")
        self._template = "{" + ",".join(keys) + "}"
        self.columns: tuple[ColumnElement[Any], ...] = tuple(columns)
        """What to select: the model's fields, each as its writer reads it."""

    def select(self) -> Select[Any]:
        """A query of the page's columns (to filter and order, then :class:`PageQuery`)."""
        return select(*self.columns)

    def items(self, rows: Sequence[Sequence[Any]]) -> list[str]:
        """The JSON objects of ``rows``."""
        written = []
        columns = zip(*rows, strict=True)  # the last one is the total
        for (write, nullable), values in zip(self._writers, columns, strict=False):
            if nullable:
                written.append(["null" if value is None else write(value) for value in values])
            else:
                written.append(list(map(write, values)))
        template = self._template
        return [template % values for values in zip(*written, strict=True)]

    def read(
        self, db: Connection, query: PageQuery, page: PageParams, params: dict[str, Any]
    ) -> bytes:
        """The page of ``query`` (of :meth:`select`'s columns) for the filters' values
        ``params``: the UTF-8 JSON of ``{"items", "total", "limit", "offset"}``."""
        rows, total = query.rows(db, page, params)
        items = ",".join(self.items(rows))
        text = f'{{"items":[{items}],"total":{total},"limit":{page.limit},"offset":{page.offset}}}'
        return text.encode()
