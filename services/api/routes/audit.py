"""The audit log (admin)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query
from sqlalchemy import select

from services.api.crud import paginate
from services.api.deps import AdminUser, DbDep, PageDep, get_current_user
from services.api.schemas.audit import AuditEntryPublic
from services.api.schemas.common import MAX_ROW_ID, NO_NUL_PATTERN, Page
from services.core.db.models import AuditEntry

router = APIRouter(prefix="/api/v1/audit", tags=["audit"], dependencies=[Depends(get_current_user)])


@router.get("")
def list_entries(
    _: AdminUser,
    db: DbDep,
    page: PageDep,
    action: Annotated[str | None, Query(max_length=64, pattern=NO_NUL_PATTERN)] = None,
    actor_id: Annotated[int | None, Query(ge=1, le=MAX_ROW_ID)] = None,
    target_type: Annotated[str | None, Query(max_length=32, pattern=NO_NUL_PATTERN)] = None,
    target_id: Annotated[str | None, Query(max_length=64, pattern=NO_NUL_PATTERN)] = None,
) -> Page[AuditEntryPublic]:
    """Audit entries, newest first (admin)."""
    query = select(AuditEntry).order_by(AuditEntry.id.desc())
    if action is not None:
        query = query.where(AuditEntry.action == action)
    if actor_id is not None:
        query = query.where(AuditEntry.actor_id == actor_id)
    if target_type is not None:
        query = query.where(AuditEntry.target_type == target_type)
    if target_id is not None:
        query = query.where(AuditEntry.target_id == target_id)
    return Page[AuditEntryPublic].model_validate(paginate(db, query, page))
