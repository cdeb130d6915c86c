"""Subjects: staff register them; deleting one with recordings is an audited admin purge."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, status
from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError

from services.api import audit
from services.api.crud import apply_update, busy_job, get_or_404, paginate
from services.api.deps import DbDep, PageDep, RowId, StaffUser, StoreDep, get_current_user
from services.api.errors import ForbiddenError
from services.api.schemas.common import NO_NUL_PATTERN, Page
from services.api.schemas.subjects import SubjectCreate, SubjectPublic, SubjectUpdate
from services.core.db.live import LiveRun
from services.core.db.models import (
    Artifact,
    Classifier,
    FeedbackLabel,
    LabSession,
    Recording,
    Subject,
)
from services.core.errors import ConflictError

router = APIRouter(
    prefix="/api/v1/subjects", tags=["subjects"], dependencies=[Depends(get_current_user)]
)


def _flush_code(db: DbDep, code: str) -> None:
    try:
        db.flush()
    except IntegrityError:
        db.rollback()
        raise ConflictError(f"subject code {code!r} is taken", field="code") from None


@router.post("", status_code=status.HTTP_201_CREATED)
def create(body: SubjectCreate, user: StaffUser, db: DbDep) -> SubjectPublic:
    """Register a subject by pseudonymous code (staff)."""
    if db.scalar(select(Subject.id).where(Subject.code == body.code)) is not None:
        raise ConflictError(f"subject code {body.code!r} is taken", field="code")
    subject = Subject(code=body.code, notes=body.notes)
    db.add(subject)
    _flush_code(db, body.code)
    audit.record(db, user, "subject.create", "subject", subject.id, code=subject.code)
    db.commit()
    return SubjectPublic.model_validate(subject)


@router.get("")
def list_subjects(
    db: DbDep,
    page: PageDep,
    code: Annotated[
        str | None,
        Query(max_length=64, pattern=NO_NUL_PATTERN, description="Codes starting with this."),
    ] = None,
) -> Page[SubjectPublic]:
    """Subjects, by code."""
    query = select(Subject).order_by(Subject.code)
    if code:
        query = query.where(Subject.code.startswith(code, autoescape=True))
    return Page[SubjectPublic].model_validate(paginate(db, query, page))


@router.get("/{subject_id}")
def read(subject_id: RowId, db: DbDep) -> SubjectPublic:
    """One subject."""
    return SubjectPublic.model_validate(get_or_404(db, Subject, subject_id, "subject_id"))


@router.patch("/{subject_id}")
def update(subject_id: RowId, body: SubjectUpdate, user: StaffUser, db: DbDep) -> SubjectPublic:
    """Change a subject's code or notes (staff)."""
    subject = get_or_404(db, Subject, subject_id, "subject_id")
    changes = apply_update(subject, body)
    _flush_code(db, subject.code)
    audit.record(db, user, "subject.update", "subject", subject.id, fields=sorted(changes))
    db.commit()
    return SubjectPublic.model_validate(subject)


@router.delete("/{subject_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete(
    subject_id: RowId,
    user: StaffUser,
    db: DbDep,
    store: StoreDep,
    purge: Annotated[
        bool,
        Query(
            description="Also delete its recorded data (recordings, classifiers, live runs, "
            "feedback labels) and their files (admin)."
        ),
    ] = False,
) -> None:
    """Delete a subject and its sessions (staff); one with recorded data (recordings,
    classifiers, live runs, feedback labels) needs an admin and purge; one a queued or
    running job works on is refused (cancel or stop it first)."""
    subject = get_or_404(db, Subject, subject_id, "subject_id")
    session_ids = set(db.scalars(select(LabSession.id).where(LabSession.subject_id == subject_id)))
    recordings = db.scalars(
        select(Recording)
        .join(LabSession, Recording.session_id == LabSession.id)
        .where(LabSession.subject_id == subject_id)
    ).all()
    classifiers = db.scalars(select(Classifier).where(Classifier.subject_id == subject_id)).all()
    job = busy_job(
        db,
        subject_id=subject_id,
        session_ids=session_ids,
        recording_ids={r.id for r in recordings},
    )
    if job is not None:
        raise ConflictError(
            f"{job.kind} job {job.id} ({job.status}) works on subject {subject.code}; "
            "cancel it or stop the session first",
            field="subject_id",
        )
    live_runs = labels = 0
    if session_ids:
        live_runs = db.scalar(select(func.count()).where(LiveRun.session_id.in_(session_ids))) or 0
        labels = (
            db.scalar(select(func.count()).where(FeedbackLabel.session_id.in_(session_ids))) or 0
        )
    if (recordings or classifiers or live_runs or labels) and not purge:
        raise ConflictError(
            f"subject {subject.code} has {len(recordings)} recording(s), {len(classifiers)} "
            f"classifier(s), {live_runs} live run(s) and {labels} feedback label(s); an admin "
            "can delete it with purge=true, which removes their files",
            field="purge",
        )
    if purge and user.role != "admin":
        raise ForbiddenError("purging a subject's data needs the admin role", field="purge")
    artifact_ids = {r.artifact_id for r in recordings}
    for clf in classifiers:
        artifact_ids.update(a for a in (clf.onnx_artifact_id, clf.torchscript_artifact_id) if a)
    artifacts = [a for a in (db.get(Artifact, i) for i in artifact_ids) if a is not None]
    for row in (*classifiers, *recordings):
        db.delete(row)
    db.flush()
    for artifact in artifacts:
        db.delete(artifact)
    db.delete(subject)
    audit.record(
        db,
        user,
        "subject.purge" if purge else "subject.delete",
        "subject",
        subject_id,
        code=subject.code,
        recordings=len(recordings),
        classifiers=len(classifiers),
        live_runs=live_runs,
        feedback_labels=labels,
        files=len(artifacts),
    )
    db.commit()
    for artifact in artifacts:
        store.delete(artifact.relpath)
