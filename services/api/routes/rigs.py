"""Rigs (EEG set-ups): admins manage them, everyone reads."""

from __future__ import annotations

from fastapi import APIRouter, Depends, status
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError

from services.api import audit
from services.api.crud import apply_update, get_or_404, paginate
from services.api.deps import AdminUser, DbDep, PageDep, RowId, get_current_user
from services.api.schemas.common import Page
from services.api.schemas.rigs import RigCreate, RigPublic, RigUpdate
from services.core.db.models import LabSession, Rig
from services.core.errors import ConflictError

router = APIRouter(prefix="/api/v1/rigs", tags=["rigs"], dependencies=[Depends(get_current_user)])


def _commit_unique(db: DbDep, name: str) -> None:
    try:
        db.commit()
    except IntegrityError:
        db.rollback()
        raise ConflictError(f"a rig named {name!r} exists", field="name") from None


@router.post("", status_code=status.HTTP_201_CREATED)
def create(body: RigCreate, admin: AdminUser, db: DbDep) -> RigPublic:
    """Add a rig (admin)."""
    rig = Rig(**body.model_dump())
    db.add(rig)
    try:
        db.flush()
    except IntegrityError:
        db.rollback()
        raise ConflictError(f"a rig named {body.name!r} exists", field="name") from None
    audit.record(db, admin, "rig.create", "rig", rig.id, name=rig.name)
    _commit_unique(db, body.name)
    return RigPublic.model_validate(rig)


@router.get("")
def list_rigs(db: DbDep, page: PageDep) -> Page[RigPublic]:
    """Every rig."""
    return Page[RigPublic].model_validate(paginate(db, select(Rig).order_by(Rig.name), page))


@router.get("/{rig_id}")
def read(rig_id: RowId, db: DbDep) -> RigPublic:
    """One rig."""
    return RigPublic.model_validate(get_or_404(db, Rig, rig_id, "rig_id"))


@router.patch("/{rig_id}")
def update(rig_id: RowId, body: RigUpdate, admin: AdminUser, db: DbDep) -> RigPublic:
    """Change a rig (admin)."""
    rig = get_or_404(db, Rig, rig_id, "rig_id")
    changes = apply_update(rig, body)
    if rig.channel_map == {}:
        rig.channel_map = None  # {} removes the map: the stream's names are standard
    audit.record(db, admin, "rig.update", "rig", rig.id, **changes)
    _commit_unique(db, rig.name)
    return RigPublic.model_validate(rig)


@router.delete("/{rig_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete(rig_id: RowId, admin: AdminUser, db: DbDep) -> None:
    """Remove a rig no session uses (admin); otherwise 409 (deactivate it instead)."""
    rig = get_or_404(db, Rig, rig_id, "rig_id")
    used = db.scalar(select(LabSession.id).where(LabSession.rig_id == rig_id).limit(1))
    if used is not None:
        raise ConflictError(
            f"rig {rig_id} is used by session {used}; set active=false instead", field="rig_id"
        )
    db.delete(rig)
    audit.record(db, admin, "rig.delete", "rig", rig_id, name=rig.name)
    db.commit()
