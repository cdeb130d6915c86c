"""Small helpers the routes share: fetch-or-404, pagination, partial updates."""

from __future__ import annotations

from typing import Any, TypeVar

from pydantic import BaseModel
from sqlalchemy import Select, func, select
from sqlalchemy.orm import Session

from services.api.deps import PageParams
from services.core.errors import NotFoundError

RowT = TypeVar("RowT")
TOTAL_COLUMN = "total_matching"
"""Name of the count column :func:`paginate` adds to a list query."""


def get_or_404(db: Session, model: type[RowT], row_id: object, field: str) -> RowT:
    """The row of ``model`` with primary key ``row_id``; 404 naming ``field`` otherwise."""
    row = db.get(model, row_id)
    if row is None:
        name = getattr(model, "__tablename__", model.__name__).rstrip("s").replace("_", " ")
        raise NotFoundError(f"no {name} with id {row_id}", field=field)
    return row


def paginate(db: Session, query: Select[Any], page: PageParams) -> dict[str, Any]:
    """``{"items", "total", "limit", "offset"}`` of ``query`` (already filtered and ordered).

    A query of one entity gives its rows as ``items``; a query of several columns gives
    one dict per row (cheaper: no ORM objects, only what the response returns). The total
    comes in the same query, as a column counted once; only a page past the end needs a
    second query for it.
    """
    count = select(func.count()).select_from(query.order_by(None).subquery()).correlate(None)
    counted = query.add_columns(count.scalar_subquery().label(TOTAL_COLUMN))
    rows = db.execute(counted.limit(page.limit).offset(page.offset)).all()
    if rows:
        total = rows[0][-1]
    elif page.offset == 0:
        total = 0
    else:  # past the end: count on its own
        total = db.scalar(count) or 0
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
