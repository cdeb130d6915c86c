"""Tables of live sessions (issue 10): one row per run, marker, epoch decision, model version
and frame shown, written as they happen so that a crashed run resumes from them.

A *live run* is one start of a lab session's calibration, test or online session (a
``live_session`` job). Its rows are numbered by ``step``, the run's action index (0-based,
unique per run). Labels are :class:`~services.core.db.models.FeedbackLabel` rows of the lab
session (one per accepted decision of an online run). Clock columns ending in ``_ts`` are
seconds on the runner's LSL clock (``local_clock``; the sim's marker timestamps use the same
clock on one host); ``*_at`` columns are UTC datetimes.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import (
    JSON,
    Boolean,
    CheckConstraint,
    Float,
    ForeignKey,
    Integer,
    String,
    Text,
    UniqueConstraint,
    func,
    select,
    update,
)
from sqlalchemy.orm import Mapped, Session, mapped_column

from services.core.db.base import Base, UtcDateTime, utcnow
from services.core.db.models import BigIntId, Job, LabSession

LIVE_MODES = ("calibration", "test", "online")
LIVE_STATUSES = ("queued", "running", "completed", "stopped", "failed")
LIVE_ACTIVE_STATUSES = ("queued", "running")
DECISION_STATUSES = ("ok", "rejected")


class LiveRun(Base):
    """One start of a lab session's live loop and what it needs to re-attach after a crash."""

    __tablename__ = "live_runs"
    __table_args__ = (
        CheckConstraint(f"mode IN {LIVE_MODES}", name="mode_allowed"),
        CheckConstraint(f"status IN {LIVE_STATUSES}", name="status_allowed"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    session_id: Mapped[int] = mapped_column(
        ForeignKey("sessions.id", ondelete="CASCADE"), index=True
    )
    job_id: Mapped[str | None] = mapped_column(ForeignKey("jobs.id", ondelete="SET NULL"))
    mode: Mapped[str] = mapped_column(String(16))
    options: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    status: Mapped[str] = mapped_column(String(16), default="queued")
    stop_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    sim_session_id: Mapped[str | None] = mapped_column(String(200))
    hf_session_id: Mapped[str | None] = mapped_column(String(64))
    hf_method: Mapped[str | None] = mapped_column(String(32))
    """The stage-2 method of an online run's HF session, as the learner created it."""
    label_channel: Mapped[str | None] = mapped_column(String(8))
    """How the labels of an online run's HF session enter Fhat (``hard`` or ``soft``)."""
    eeg_classifier_id: Mapped[str | None] = mapped_column(String(64))
    recording_id: Mapped[int | None] = mapped_column(
        ForeignKey("recordings.id", ondelete="SET NULL")
    )
    hf_model_id: Mapped[int | None] = mapped_column(ForeignKey("hf_models.id", ondelete="SET NULL"))
    follow_up_job_id: Mapped[str | None] = mapped_column(ForeignKey("jobs.id", ondelete="SET NULL"))
    """The eeg_calibration job a calibration run started."""
    resumes: Mapped[int] = mapped_column(Integer, default=0)
    """Times the run re-attached after a crash of the worker or of a service."""
    result: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    error: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow, onupdate=utcnow)
    finished_at: Mapped[datetime | None] = mapped_column(UtcDateTime)


def queue_live_job(db: Session, run: LiveRun, kind: str, **job_fields: Any) -> Job:
    """Add the queued job of ``kind`` (the job contract's live session kind, which core
    cannot import) that runs ``run`` and point ``run.job_id`` at it.

    The job's config is the lab session, the run and the run's options; ``job_fields`` are
    further :class:`~services.core.db.models.Job` columns (submitter, attempts). The caller
    commits.
    """
    config = {"session_id": run.session_id, "run_id": run.id, **run.options}
    job = Job(kind=kind, config=config, status="queued", **job_fields)
    db.add(job)
    db.flush()
    run.job_id = job.id
    return job


class LiveMarker(Base):
    """One executed action: the sim's marker (oracle label) and the state it was taken in."""

    __tablename__ = "live_markers"
    __table_args__ = (UniqueConstraint("run_id", "step", name="uq_live_markers_step"),)

    id: Mapped[int] = mapped_column(BigIntId, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("live_runs.id", ondelete="CASCADE"))
    session_id: Mapped[int] = mapped_column(
        ForeignKey("sessions.id", ondelete="CASCADE"), index=True
    )
    step: Mapped[int] = mapped_column(Integer)
    sim_session_id: Mapped[str] = mapped_column(String(200))
    sim_step: Mapped[int] = mapped_column(Integer)
    episode: Mapped[int] = mapped_column(Integer)
    action: Mapped[int] = mapped_column(Integer)
    oracle_correct: Mapped[bool | None] = mapped_column(Boolean)
    observation: Mapped[list[float]] = mapped_column(JSON)
    policy_version: Mapped[int | None] = mapped_column(Integer)
    """pi_HF's model version that chose the action (online runs)."""
    marker_ts: Mapped[float] = mapped_column(Float)
    """The sim's marker timestamp (LSL clock): when the action was executed."""
    eeg_ts: Mapped[float] = mapped_column(Float)
    """The marker's time on the EEG stream's clock (the virtual clock when accelerated)."""
    executed_at: Mapped[datetime] = mapped_column(UtcDateTime)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)


class LiveDecision(Base):
    """The EEG service's decision on the epoch after one marker (accepted or rejected, why)."""

    __tablename__ = "live_decisions"
    __table_args__ = (
        UniqueConstraint("run_id", "step", name="uq_live_decisions_step"),
        CheckConstraint(f"status IN {DECISION_STATUSES}", name="status_allowed"),
    )

    id: Mapped[int] = mapped_column(BigIntId, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("live_runs.id", ondelete="CASCADE"))
    session_id: Mapped[int] = mapped_column(
        ForeignKey("sessions.id", ondelete="CASCADE"), index=True
    )
    step: Mapped[int] = mapped_column(Integer)
    status: Mapped[str] = mapped_column(String(16))
    reason: Mapped[str | None] = mapped_column(Text)
    feedback: Mapped[str | None] = mapped_column(String(16))
    p_error: Mapped[float | None] = mapped_column(Float)
    log_likelihood_ratio: Mapped[float | None] = mapped_column(Float)
    """log P(epoch | error) / P(epoch | correct) from a calibrated classifier (the soft label)."""
    oracle_correct: Mapped[bool | None] = mapped_column(Boolean)
    classifier_id: Mapped[str | None] = mapped_column(String(64))
    epoch_end_ts: Mapped[float | None] = mapped_column(Float)
    """When the epoch's last sample was in the EEG service (runner clock)."""
    decided_ts: Mapped[float] = mapped_column(Float)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)


class LiveModelVersion(Base):
    """The learner's state after one label of an online run (and when the next action was
    ready)."""

    __tablename__ = "live_model_versions"
    __table_args__ = (UniqueConstraint("run_id", "step", name="uq_live_model_versions_step"),)

    id: Mapped[int] = mapped_column(BigIntId, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("live_runs.id", ondelete="CASCADE"))
    session_id: Mapped[int] = mapped_column(
        ForeignKey("sessions.id", ondelete="CASCADE"), index=True
    )
    step: Mapped[int] = mapped_column(Integer)
    labels: Mapped[int] = mapped_column(Integer)
    model_version: Mapped[int] = mapped_column(Integer)
    metrics: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    updated_ts: Mapped[float] = mapped_column(Float)
    """When the learner answered the label (runner clock)."""
    next_ready_ts: Mapped[float | None] = mapped_column(Float)
    """When pi_HF's next action was known (runner clock)."""
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)


class LiveFrameShown(Base):
    """When the subject's display actually showed the frame of one action."""

    __tablename__ = "live_frames_shown"
    __table_args__ = (UniqueConstraint("run_id", "step", name="uq_live_frames_shown_step"),)

    id: Mapped[int] = mapped_column(BigIntId, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("live_runs.id", ondelete="CASCADE"))
    session_id: Mapped[int] = mapped_column(
        ForeignKey("sessions.id", ondelete="CASCADE"), index=True
    )
    step: Mapped[int] = mapped_column(Integer)
    shown_at: Mapped[datetime] = mapped_column(UtcDateTime)
    received_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)


def end_live_run(db: Session, run_id: int, reason: str) -> bool:
    """End a live run that cannot go on (its job failed: a service stayed down, or its
    worker died on the last attempt) and its lab session, saying why; the rows written so
    far (markers, decisions, labels, the recording) stay, and starting the session again
    resumes from them. A run already ended is left alone; returns whether this call ended
    it. Commits."""
    steps = db.scalar(select(func.count()).where(LiveMarker.run_id == run_id)) or 0
    error = (
        f"session ended after {steps} steps: {reason}; its markers, decisions and labels "
        "are kept, start the session again to resume"
    )
    ended = db.execute(
        update(LiveRun)
        .where(LiveRun.id == run_id, LiveRun.status.in_(LIVE_ACTIVE_STATUSES))
        .values(status="failed", error=error, finished_at=utcnow(), updated_at=utcnow())
        .execution_options(synchronize_session=False)
    ).rowcount
    if ended == 1:
        session_id = select(LiveRun.session_id).where(LiveRun.id == run_id).scalar_subquery()
        db.execute(
            update(LabSession)
            .where(LabSession.id == session_id, LabSession.status == "running")
            .values(status="failed", updated_at=utcnow())
            .execution_options(synchronize_session=False)
        )
    db.commit()
    return ended == 1


def end_live_runs_of_job(db: Session, job_id: str, reason: str) -> None:
    """:func:`end_live_run` for the runs of a ``live_session`` job that was failed outside
    its handler (by the reaper, or by the worker after the handler raised): nothing for a
    job of another kind. Commits."""
    runs = db.scalars(
        select(LiveRun.id).where(LiveRun.job_id == job_id, LiveRun.status.in_(LIVE_ACTIVE_STATUSES))
    ).all()
    for run_id in runs:
        end_live_run(db, run_id, reason)
