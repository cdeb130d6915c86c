"""Lab sessions: schedule, reschedule, cancel; no two at once for a subject or a rig."""

from __future__ import annotations

from datetime import UTC, date, datetime, timedelta
from typing import Annotated
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from fastapi import APIRouter, Depends, Query
from sqlalchemy import Select, false, or_, select, text
from sqlalchemy import update as sql_update
from sqlalchemy.orm import Session

from services.api import audit
from services.api.crud import get_or_404, paginate
from services.api.deps import DbDep, PageDep, RowId, StaffUser, get_current_user
from services.api.schemas.common import MAX_ROW_ID, Page
from services.api.schemas.sessions import (
    SessionCreate,
    SessionPublic,
    SessionStatus,
    SessionUpdate,
)
from services.core.db.models import LabSession, Rig, Subject, User
from services.core.errors import BadRequestError, ConflictError

router = APIRouter(
    prefix="/api/v1/sessions", tags=["sessions"], dependencies=[Depends(get_current_user)]
)

ACTIVE_STATUSES = ("scheduled", "running")
"""Sessions that occupy their subject and rig (cancelled, failed and completed ones do not)."""
NEXT_STATUSES = {
    "scheduled": {"running", "failed"},
    "running": {"completed", "failed"},
}
"""Status changes allowed through PATCH (cancel has its own route)."""
PAST_GRACE = timedelta(minutes=5)
"""A start this recent is not "in the past" (the form was filled in a few minutes ago)."""


def _refuse_past(scheduled_at: datetime, allow_past: bool) -> None:
    """422 at ``scheduled_at`` if it is in the past (by more than :data:`PAST_GRACE`) and
    the request does not confirm it with ``allow_past``."""
    if allow_past or scheduled_at >= datetime.now(UTC) - PAST_GRACE:
        return
    raise BadRequestError(
        f"starts in the past ({scheduled_at:%Y-%m-%d %H:%M} UTC); send allow_past: true to "
        "schedule it anyway (a session that has happened)",
        field="scheduled_at",
    )


def _check_refs(
    db: Session, subject_id: int | None, rig_id: int | None, operator_id: int | None
) -> None:
    if subject_id is not None and db.get(Subject, subject_id) is None:
        raise BadRequestError(f"no subject with id {subject_id}", field="subject_id")
    if rig_id is not None:
        rig = db.get(Rig, rig_id)
        if rig is None:
            raise BadRequestError(f"no rig with id {rig_id}", field="rig_id")
        if not rig.active:
            raise BadRequestError(f"rig {rig.name} is not active", field="rig_id")
    if operator_id is not None and db.get(User, operator_id) is None:
        raise BadRequestError(f"no user with id {operator_id}", field="operator_id")


PG_LOCK_SPACE_SUBJECT = 0x62677375
PG_LOCK_SPACE_RIG = 0x62677269
"""First keys of the PostgreSQL advisory locks that serialise one subject's, one rig's
scheduling."""


def _lock_schedule(db: Session, session: LabSession) -> None:
    """Hold, until the transaction ends, the right to schedule the session's subject and rig,
    so that the overlap check and the write of racing requests cannot interleave.

    PostgreSQL: an advisory lock per subject, then per rig (always in that order: no
    deadlock). SQLite: the database's write lock, taken by a write that changes nothing
    before the check reads (a read-then-write transaction would lose the race in WAL mode).
    """
    if db.get_bind().dialect.name == "postgresql":
        keys = [(PG_LOCK_SPACE_SUBJECT, session.subject_id)]
        if session.rig_id is not None:
            keys.append((PG_LOCK_SPACE_RIG, session.rig_id))
        for space, key in keys:
            db.execute(
                text("SELECT pg_advisory_xact_lock(:space, :key)"), {"space": space, "key": key}
            )
    else:
        db.execute(sql_update(LabSession).where(false()).values(id=LabSession.id))


def _refuse_overlap(db: Session, session: LabSession) -> None:
    """409 naming the other session if this one overlaps one of its subject or rig (under
    :func:`_lock_schedule`, held until the caller commits)."""
    _lock_schedule(db, session)
    clash = [LabSession.subject_id == session.subject_id]
    if session.rig_id is not None:
        clash.append(LabSession.rig_id == session.rig_id)
    query = (
        select(LabSession)
        .where(
            or_(*clash),
            LabSession.status.in_(ACTIVE_STATUSES),
            LabSession.scheduled_at < session.ends_at,
            LabSession.ends_at > session.scheduled_at,
        )
        .order_by(LabSession.scheduled_at)
        .limit(1)
    )
    if session.id is not None:
        query = query.where(LabSession.id != session.id)
    other = db.scalar(query)
    if other is not None:
        shared = "subject" if other.subject_id == session.subject_id else "rig"
        raise ConflictError(
            f"overlaps session {other.id} of the same {shared} "
            f"({other.scheduled_at.isoformat()} to {other.ends_at.isoformat()})",
            field="scheduled_at",
        )


@router.post("", status_code=201)
def create(body: SessionCreate, user: StaffUser, db: DbDep) -> SessionPublic:
    """Schedule a session (staff); 409 if it overlaps one of the same subject or rig, 422 if
    it starts in the past unless ``allow_past`` confirms it."""
    _check_refs(db, body.subject_id, body.rig_id, body.operator_id)
    _refuse_past(body.scheduled_at, body.allow_past)
    session = LabSession(
        subject_id=body.subject_id,
        rig_id=body.rig_id,
        kind=body.kind,
        scheduled_at=body.scheduled_at,
        duration_minutes=body.duration_minutes,
        ends_at=body.scheduled_at + timedelta(minutes=body.duration_minutes),
        status="scheduled",
        operator_id=body.operator_id if body.operator_id is not None else user.id,
        notes=body.notes,
    )
    _refuse_overlap(db, session)
    db.add(session)
    db.flush()
    audit.record(db, user, "session.create", "session", session.id, subject_id=session.subject_id)
    db.commit()
    return SessionPublic.model_validate(session)


def _period(day: date | None, week: str | None, tz_name: str) -> tuple[datetime, datetime] | None:
    try:
        period = _local_period(day, week, tz_name)
        return None if period is None else (period[0].astimezone(UTC), period[1].astimezone(UTC))
    except OverflowError:  # a day or week at the very end of the calendar
        field = "day" if day is not None else "week"
        raise BadRequestError(
            f"{field} {day or week} is out of the calendar's range", field=field
        ) from None


def _local_period(
    day: date | None, week: str | None, tz_name: str
) -> tuple[datetime, datetime] | None:
    try:
        tz = ZoneInfo(tz_name)
    except (ZoneInfoNotFoundError, ValueError):
        raise BadRequestError(f"unknown time zone {tz_name!r}", field="tz") from None
    if day is not None and week is not None:
        raise BadRequestError("give day or week, not both", field="week")
    if day is not None:
        start = datetime.combine(day, datetime.min.time(), tz)
        return start, start + timedelta(days=1)
    if week is not None:
        try:
            monday = datetime.strptime(week + "-1", "%G-W%V-%u").date()
        except ValueError:
            raise BadRequestError(
                f"week {week!r} is not an ISO week like 2026-W49", field="week"
            ) from None
        start = datetime.combine(monday, datetime.min.time(), tz)
        return start, start + timedelta(days=7)
    return None


@router.get("")
def list_sessions(
    db: DbDep,
    page: PageDep,
    day: Annotated[
        date | None, Query(description="Sessions starting on this day (YYYY-MM-DD).")
    ] = None,
    week: Annotated[
        str | None, Query(pattern=r"^\d{4}-W\d{2}$", description="ISO week, e.g. 2026-W49.")
    ] = None,
    tz: Annotated[str, Query(max_length=64, description="Time zone of day/week.")] = "UTC",
    subject_id: Annotated[int | None, Query(ge=1, le=MAX_ROW_ID)] = None,
    rig_id: Annotated[int | None, Query(ge=1, le=MAX_ROW_ID)] = None,
    status: Annotated[SessionStatus | None, Query()] = None,
) -> Page[SessionPublic]:
    """Sessions in time order, by day or ISO week, subject, rig or status."""
    query: Select[tuple[LabSession]] = select(LabSession).order_by(
        LabSession.scheduled_at, LabSession.id
    )
    period = _period(day, week, tz)
    if period is not None:
        query = query.where(
            LabSession.scheduled_at >= period[0], LabSession.scheduled_at < period[1]
        )
    if subject_id is not None:
        query = query.where(LabSession.subject_id == subject_id)
    if rig_id is not None:
        query = query.where(LabSession.rig_id == rig_id)
    if status is not None:
        query = query.where(LabSession.status == status)
    return Page[SessionPublic].model_validate(paginate(db, query, page))


@router.get("/{session_id}")
def read(session_id: RowId, db: DbDep) -> SessionPublic:
    """One session."""
    return SessionPublic.model_validate(get_or_404(db, LabSession, session_id, "session_id"))


@router.patch("/{session_id}")
def update(session_id: RowId, body: SessionUpdate, user: StaffUser, db: DbDep) -> SessionPublic:
    """Reschedule or edit a session, or move its status along (staff); a new start in the
    past needs ``allow_past``."""
    session = get_or_404(db, LabSession, session_id, "session_id")
    changes = body.model_dump(exclude_unset=True)
    allow_past = changes.pop("allow_past", False)
    timing = {"scheduled_at", "duration_minutes", "rig_id", "kind"} & changes.keys()
    if timing and session.status != "scheduled":
        raise ConflictError(
            f"session {session_id} is {session.status}; only a scheduled one can be rescheduled",
            field=sorted(timing)[0],
        )
    if "status" in changes and changes["status"] is not None:
        allowed = NEXT_STATUSES.get(session.status, set())
        if changes["status"] not in allowed:
            raise ConflictError(
                f"session {session_id} is {session.status}; it cannot become {changes['status']}",
                field="status",
            )
    _check_refs(db, None, changes.get("rig_id"), changes.get("operator_id"))
    new_start = changes.get("scheduled_at")
    if new_start is not None and new_start != session.scheduled_at:
        _refuse_past(new_start, allow_past)
    for key in ("kind", "scheduled_at", "duration_minutes", "operator_id", "notes", "status"):
        if changes.get(key) is not None:
            setattr(session, key, changes[key])
    if "rig_id" in changes:
        session.rig_id = changes["rig_id"]  # null moves the session off any rig
    session.ends_at = session.scheduled_at + timedelta(minutes=session.duration_minutes)
    if timing:
        _refuse_overlap(db, session)
    audit.record(db, user, "session.update", "session", session.id, fields=sorted(changes))
    db.commit()
    return SessionPublic.model_validate(session)


@router.post("/{session_id}/cancel")
def cancel(session_id: RowId, user: StaffUser, db: DbDep) -> SessionPublic:
    """Cancel a scheduled session (staff); its slot is free again."""
    session = get_or_404(db, LabSession, session_id, "session_id")
    if session.status != "scheduled":
        raise ConflictError(
            f"session {session_id} is {session.status}; only a scheduled one can be cancelled",
            field="session_id",
        )
    session.status = "cancelled"
    audit.record(db, user, "session.cancel", "session", session.id)
    db.commit()
    return SessionPublic.model_validate(session)
