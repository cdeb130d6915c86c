"""Small helpers the routes share: fetch-or-404, pagination, partial updates."""

from __future__ import annotations

from typing import Any, TypeVar

from pydantic import BaseModel
from sqlalchemy import Select, func, select
from sqlalchemy.orm import Session

from services.api.deps import PageParams
from services.core.errors import NotFoundError

RowT = TypeVar("RowT")


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
    one dict per row (cheaper: no ORM objects, only what the response returns).
    """
    total = db.scalar(select(func.count()).select_from(query.order_by(None).subquery())) or 0
    result = db.execute(query.limit(page.limit).offset(page.offset))
    if len(query.column_descriptions) == 1:
        items: list[Any] = result.scalars().all()
    else:
        items = [row._asdict() for row in result]
    return {"items": items, "total": total, "limit": page.limit, "offset": page.offset}


def apply_update(row: object, update: BaseModel) -> dict[str, Any]:
    """Set the fields given (not null) in ``update`` on ``row``; the changes made."""
    changes = update.model_dump(exclude_unset=True, exclude_none=True)
    for key, value in changes.items():
        setattr(row, key, value)
    return changes
