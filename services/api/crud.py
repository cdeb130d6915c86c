"""Small helpers the routes share: fetch-or-404, pagination, partial updates."""

from __future__ import annotations

from collections.abc import Collection, Sequence
from typing import Any, TypeVar

from pydantic import BaseModel
from sqlalchemy import (
    Select,
    bindparam,
    func,
    select,
)
from sqlalchemy.engine import Connection
from sqlalchemy.orm import Session

from services.api.deps import PageParams
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


class PageQuery:
    """A list query (filtered and ordered) with its count, limit and offset, built once: a
    route that lists often keeps one (its filters' values as bind parameters), since
    building a query with its count costs more CPU than running it."""

    def __init__(self, query: Select[Any]) -> None:
        names = [column["name"] for column in query.column_descriptions]
        self.names: list[str] | None = names if len(names) > 1 else None
        """The names of the columns selected, or None for a query of one entity."""
        self.count: Select[Any] = (
            select(func.count()).select_from(query.order_by(None).subquery()).correlate(None)
        )
        """The number of rows ``query`` matches."""
        self.page: Select[Any] = (
            query.add_columns(self.count.scalar_subquery().label(TOTAL_COLUMN))
            .limit(bindparam("page_limit"))
            .offset(bindparam("page_offset"))
        )
        """One page of ``query``, each row ending with the total matching (counted once, in
        the same query; only a page past the end needs a second query for it)."""

    def rows(
        self, db: Session | Connection, page: PageParams, params: dict[str, Any] | None = None
    ) -> tuple[Sequence[Any], int]:
        """The rows on ``page`` (each ending with the total) and the total matching, for the
        filters' values ``params``."""
        params = params or {}
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

    def paginate(
        self, db: Session | Connection, page: PageParams, params: dict[str, Any] | None = None
    ) -> dict[str, Any]:
        """``{"items", "total", "limit", "offset"}``: a query of one entity gives its rows
        as ``items``; a query of columns gives one dict per row (cheaper: no ORM objects,
        only what the response returns; cheaper still on the session's ``connection()``,
        which skips the ORM's handling of rows)."""
        rows, total = self.rows(db, page, params)
        names = self.names
        if names is None:
            items: list[Any] = [row[0] for row in rows]
        else:
            items = [dict(zip(names, row[:-1], strict=True)) for row in rows]
        return {"items": items, "total": total, "limit": page.limit, "offset": page.offset}


def paginate(db: Session, query: Select[Any], page: PageParams) -> dict[str, Any]:
    """``{"items", "total", "limit", "offset"}`` of ``query`` (already filtered and ordered),
    on ``page`` (:meth:`PageQuery.paginate`)."""
    return PageQuery(query).paginate(db, page)


def apply_update(row: object, update: BaseModel) -> dict[str, Any]:
    """Set the fields given (not null) in ``update`` on ``row``; the changes made."""
    changes = update.model_dump(exclude_unset=True, exclude_none=True)
    for key, value in changes.items():
        setattr(row, key, value)
    return changes
