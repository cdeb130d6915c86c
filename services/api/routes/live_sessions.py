"""Live sessions: start and stop a lab session's calibration, test or online loop, follow it
(status, counts, running accuracy, labels vs budget, latencies), read its events, and take
the subject display's frame-shown times."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Query
from pydantic import BaseModel, Field
from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from services.api import audit
from services.api.crud import get_or_404
from services.api.deps import (
    CeleryDep,
    DbDep,
    PageDep,
    RowId,
    SettingsDep,
    StaffUser,
    get_current_user,
)
from services.api.routes.jobs import _enqueue, require_job_space
from services.api.schemas.common import MAX_ROW_ID, ApiRequest, UtcDatetime, unstorable_text
from services.core.db.live import (
    LiveDecision,
    LiveFrameShown,
    LiveMarker,
    LiveModelVersion,
    LiveRun,
    queue_live_job,
)
from services.core.db.models import Classifier, FeedbackLabel, Job, LabSession
from services.core.errors import BadRequestError, ConflictError, NotFoundError
from services.core.live import (
    LiveOptions,
    latency_summary,
    pace_drift,
    soft_channel_refusal,
    timeline_latencies,
)
from services.platform.jobs import LIVE_SESSION

router = APIRouter(
    prefix="/api/v1/sessions", tags=["live sessions"], dependencies=[Depends(get_current_user)]
)

LIVE_KINDS = ("calibration", "test", "online")
ACTIVE_RUN = ("queued", "running")


class LiveRunPublic(BaseModel):
    """A live run of a session."""

    model_config = {"from_attributes": True}

    id: int
    session_id: int
    job_id: str | None
    mode: str
    options: dict[str, Any]
    hf_method: str | None = Field(
        description="Stage-2 method of an online run's pi_HF (known once the run started)."
    )
    label_channel: str | None = Field(
        description="How an online run's labels enter Fhat, 'hard' or 'soft' (known once the "
        "run started)."
    )
    status: str
    stop_requested: bool
    resumes: int
    recording_id: int | None
    hf_model_id: int | None
    follow_up_job_id: str | None
    result: dict[str, Any] | None
    error: str | None
    created_at: datetime
    finished_at: datetime | None


class LiveStatusPublic(BaseModel):
    """What a live session is doing: counts, accuracy, labels, latencies (ms)."""

    run: LiveRunPublic
    job_status: str | None
    job_error: str | None
    markers: int
    decisions_accepted: int
    decisions_rejected: int
    running_accuracy: float | None = Field(description="Accepted decisions matching the oracle.")
    labels: int
    label_budget: int | None
    latency: dict[str, dict[str, float | int | None]]
    pace: dict[str, float | None] | None


class FrameShown(ApiRequest):
    """When the subject's display showed the frame of action ``step``."""

    step: int = Field(ge=0, le=10**7)
    shown_at: UtcDatetime


def _latest_run(db: Session, session_id: int) -> LiveRun | None:
    return db.scalar(
        select(LiveRun).where(LiveRun.session_id == session_id).order_by(LiveRun.id.desc())
    )


def _run_or_404(db: Session, session_id: int) -> LiveRun:
    run = _latest_run(db, session_id)
    if run is None:
        raise NotFoundError(f"session {session_id} was never started", field="session_id")
    return run


@router.post("/{session_id}/start", status_code=201)
def start(
    session_id: RowId,
    body: LiveOptions,
    user: StaffUser,
    db: DbDep,
    celery: CeleryDep,
    settings: SettingsDep,
) -> LiveRunPublic:
    """Start (or resume, after a failure) the session's live loop as a ``live_session`` job.

    Refused with 507 while the data disk keeps less than ``BGRL_MIN_FREE_MB`` free (the
    session records EEG and labels as it runs).
    """
    require_job_space(settings, "starting a live session")
    lab = get_or_404(db, LabSession, session_id, "session_id")
    for name, value in body:
        if (problem := unstorable_text(value)) is not None:
            raise BadRequestError(problem, field=name)
    if lab.kind not in LIVE_KINDS:
        raise BadRequestError(
            f"session {session_id} is a {lab.kind} session; only {', '.join(LIVE_KINDS)} run live",
            field="session_id",
        )
    for online_only in ("hf_method", "label_channel"):
        if getattr(body, online_only) is not None and lab.kind != "online":
            raise BadRequestError(
                f"{online_only} applies to online sessions, not to a {lab.kind} session",
                field=online_only,
            )
    if lab.kind in ("test", "online"):
        if body.classifier_id is None:
            raise BadRequestError(f"{lab.kind} sessions need a classifier", field="classifier_id")
        too_big = body.classifier_id > MAX_ROW_ID  # PostgreSQL's integer would overflow
        classifier = None if too_big else db.get(Classifier, body.classifier_id)
        if classifier is None:
            raise BadRequestError(f"no classifier {body.classifier_id}", field="classifier_id")
        refusal = soft_channel_refusal(classifier.metrics)
        if body.label_channel == "soft" and refusal is not None:
            raise BadRequestError(
                f"classifier {body.classifier_id} {refusal}: the soft channel needs a "
                "calibrated posterior; calibrate again (eeg_calibration) or use label_channel "
                "hard",
                field="label_channel",
            )
    run = _latest_run(db, session_id)
    job = db.get(Job, run.job_id) if run is not None and run.job_id else None
    active = job is not None and job.status in ("queued", "running")
    if run is not None and run.status in ACTIVE_RUN and active:
        raise ConflictError(f"session {session_id} is already running", field="session_id")
    options = body.model_dump(mode="json", exclude_none=True)
    if run is None or run.status in ("completed", "stopped"):
        if lab.status not in ("scheduled", "running"):
            raise ConflictError(f"session {session_id} is {lab.status}", field="session_id")
        if run is not None:
            raise ConflictError(f"session {session_id} already ran", field="session_id")
        run = LiveRun(session_id=session_id, mode=lab.kind, options=options, status="queued")
        db.add(run)
        db.flush()
    else:  # a failed or abandoned run resumes from its rows with the options it began with
        run.status, run.error, run.stop_requested = "queued", None, False
    job = queue_live_job(
        db, run, LIVE_SESSION.name, submitter_id=user.id, max_attempts=settings.job_max_attempts
    )
    lab.status = "running"
    audit.record(db, user, "session.start", "session", session_id, job_id=job.id)
    db.commit()
    _enqueue(celery, job)
    db.refresh(run)
    return LiveRunPublic.model_validate(run)


@router.post("/{session_id}/stop")
def stop(session_id: RowId, user: StaffUser, db: DbDep) -> LiveRunPublic:
    """Ask the live loop to stop after the current action (the session then ends normally:
    calibration stores its recording, online exports its HF model)."""
    get_or_404(db, LabSession, session_id, "session_id")
    run = _run_or_404(db, session_id)
    if run.status not in ACTIVE_RUN:
        raise ConflictError(
            f"session {session_id} is not running ({run.status})", field="session_id"
        )
    run.stop_requested = True
    audit.record(db, user, "session.stop", "session", session_id)
    db.commit()
    db.refresh(run)
    return LiveRunPublic.model_validate(run)


def _latency(db: Session, run: LiveRun) -> dict[str, list[float]]:
    markers = {
        step: (ts, executed.timestamp())
        for step, ts, executed in db.execute(
            select(LiveMarker.step, LiveMarker.marker_ts, LiveMarker.executed_at).where(
                LiveMarker.run_id == run.id
            )
        )
    }
    decisions = {
        step: (end, decided)
        for step, end, decided in db.execute(
            select(LiveDecision.step, LiveDecision.epoch_end_ts, LiveDecision.decided_ts).where(
                LiveDecision.run_id == run.id
            )
        )
    }
    versions = {
        step: (updated, ready)
        for step, updated, ready in db.execute(
            select(
                LiveModelVersion.step, LiveModelVersion.updated_ts, LiveModelVersion.next_ready_ts
            ).where(LiveModelVersion.run_id == run.id)
        )
    }
    frames = [
        shown.timestamp() - markers[step][1]
        for step, shown in db.execute(
            select(LiveFrameShown.step, LiveFrameShown.shown_at).where(
                LiveFrameShown.run_id == run.id
            )
        )
        if step in markers
    ]
    return timeline_latencies(markers, decisions, versions, frames)


@router.get("/{session_id}/live")
def live(session_id: RowId, db: DbDep) -> LiveStatusPublic:
    """The live loop now: run and job status, counts, running accuracy, labels vs budget,
    latency percentiles (ms) and, for paced runs, the pace's drift."""
    get_or_404(db, LabSession, session_id, "session_id")
    run = _run_or_404(db, session_id)
    job = db.get(Job, run.job_id) if run.job_id else None
    n_markers = db.scalar(select(func.count()).where(LiveMarker.run_id == run.id)) or 0
    rows = db.execute(
        select(LiveDecision.status, LiveDecision.feedback, LiveDecision.oracle_correct).where(
            LiveDecision.run_id == run.id
        )
    ).all()
    accepted = [r for r in rows if r.status == "ok" and r.oracle_correct is not None]
    hits = sum(1 for r in accepted if (r.feedback == "correct") == r.oracle_correct)
    labels = db.scalar(select(func.count()).where(FeedbackLabel.session_id == session_id)) or 0
    pace = None
    if not run.options.get("accelerated", False):
        stamps = db.scalars(
            select(LiveMarker.marker_ts)
            .where(LiveMarker.run_id == run.id)
            .order_by(LiveMarker.step)
        ).all()
        pace = pace_drift(list(stamps), float(run.options.get("period_s", 1.5)))
    return LiveStatusPublic(
        run=LiveRunPublic.model_validate(run),
        job_status=job.status if job else None,
        job_error=job.error if job else None,
        markers=n_markers,
        decisions_accepted=sum(1 for r in rows if r.status == "ok"),
        decisions_rejected=sum(1 for r in rows if r.status == "rejected"),
        running_accuracy=hits / len(accepted) if accepted else None,
        labels=labels,
        label_budget=run.options.get("label_budget", 1000) if run.mode == "online" else None,
        latency=latency_summary(_latency(db, run)),
        pace=pace,
    )


EVENT_TABLES: dict[str, Any] = {
    "markers": LiveMarker,
    "decisions": LiveDecision,
    "model_versions": LiveModelVersion,
    "frames": LiveFrameShown,
}
SKIP = {"_sa_instance_state"}


@router.get("/{session_id}/events")
def events(
    session_id: RowId,
    db: DbDep,
    page: PageDep,
    kind: Annotated[
        Literal["markers", "decisions", "labels", "model_versions", "frames"], Query()
    ] = "markers",
    since_step: Annotated[int, Query(ge=0, le=10**7)] = 0,
) -> dict[str, Any]:
    """One kind of event of the session's latest run, by step (paginated)."""
    get_or_404(db, LabSession, session_id, "session_id")
    if kind == "labels":
        model: Any = FeedbackLabel
        query = select(FeedbackLabel).where(FeedbackLabel.session_id == session_id)
    else:
        model = EVENT_TABLES[kind]
        run = _run_or_404(db, session_id)
        query = select(model).where(model.run_id == run.id)
    query = query.where(model.step >= since_step).order_by(model.step)
    total = db.scalar(select(func.count()).select_from(query.subquery())) or 0
    items = db.scalars(query.limit(page.limit).offset(page.offset)).all()
    return {
        "kind": kind,
        "items": [{k: v for k, v in vars(i).items() if k not in SKIP} for i in items],
        "total": total,
        "limit": page.limit,
        "offset": page.offset,
    }


@router.post("/{session_id}/frames-shown", status_code=201)
def frame_shown(session_id: RowId, body: FrameShown, db: DbDep) -> dict[str, Any]:
    """The subject display reports when the frame of action ``step`` was on screen (the
    screen-to-decision latency of each action is measured from it)."""
    get_or_404(db, LabSession, session_id, "session_id")
    run = _run_or_404(db, session_id)
    row = LiveFrameShown(
        run_id=run.id, session_id=session_id, step=body.step, shown_at=body.shown_at
    )
    db.add(row)
    try:
        db.commit()
    except IntegrityError:
        db.rollback()
        raise ConflictError(
            f"the frame of step {body.step} was already reported", field="step"
        ) from None
    return {"run_id": run.id, "step": body.step, "shown_at": body.shown_at.isoformat()}
