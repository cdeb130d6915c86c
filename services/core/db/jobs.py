"""Leases on job rows: claim, heartbeat, progress, finish, and the reaper of dead workers.

A worker may write to a job only while it holds the job's lease (``lease_owner`` is its id and
``lease_expires_at`` is in the future). Every write here is one conditional ``UPDATE``, so two
workers that receive the same job id (a duplicate message, or the reaper's re-send racing a
slow worker) cannot both run it: exactly one claim matches, and a worker that lost its lease
(e.g. paused past it) finds its next heartbeat refused and stops without writing.

``attempts`` counts claims; a job is claimed at most ``max_attempts`` times, after which it is
marked failed. A reproduction's parent job waits for its runs holding no lease (status
``running``, ``lease_owner`` NULL); :func:`wait_for_children` gives it its attempts back,
since fanning out is idempotent and only the final aggregation can still fail.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import and_, func, or_, select, update
from sqlalchemy.orm import Session

from services.core.db.base import utcnow
from services.core.db.live import end_live_runs_of_job
from services.core.db.models import JOB_FINAL_STATUSES, AuditEntry, Job


class ClaimOutcome(enum.Enum):
    """What :func:`claim_job` found."""

    CLAIMED = "claimed"
    """The caller now holds the lease and runs the job."""
    MISSING = "missing"
    """No such job (deleted): drop the message."""
    FINISHED = "finished"
    """Already succeeded, failed or cancelled: drop the message."""
    LEASED = "leased"
    """Another live worker holds the lease: drop the message."""
    CANCELLED = "cancelled"
    """Cancel was requested before it started: now marked cancelled."""
    EXHAUSTED = "exhausted"
    """No attempts left: now marked failed."""


@dataclass(frozen=True)
class Heartbeat:
    """Answer of :func:`heartbeat`."""

    held: bool
    """The caller still holds the lease (False: stop at once and write nothing more)."""
    cancel_requested: bool
    """Someone asked to cancel the job."""


def _lease_free(now: datetime) -> Any:
    return or_(
        Job.lease_owner.is_(None), Job.lease_expires_at.is_(None), Job.lease_expires_at < now
    )


def _held_by(job_id: str, owner: str) -> Any:
    return and_(Job.id == job_id, Job.lease_owner == owner, Job.status == "running")


def claim_job(session: Session, job_id: str, owner: str, lease_s: float) -> ClaimOutcome:
    """Take the lease of a queued job, or of a running one whose lease expired."""
    now = utcnow()
    claimed = session.execute(
        update(Job)
        .where(
            Job.id == job_id,
            Job.status.in_(("queued", "running")),
            Job.cancel_requested.is_(False),
            Job.attempts < Job.max_attempts,
            _lease_free(now),
        )
        .values(
            status="running",
            lease_owner=owner,
            lease_expires_at=now + timedelta(seconds=lease_s),
            heartbeat_at=now,
            attempts=Job.attempts + 1,
            started_at=func.coalesce(Job.started_at, now),
            finished_at=None,
        )
        .execution_options(synchronize_session=False)
    ).rowcount
    session.commit()
    if claimed == 1:
        return ClaimOutcome.CLAIMED
    job = session.get(Job, job_id, populate_existing=True)
    if job is None:
        return ClaimOutcome.MISSING
    if job.status in JOB_FINAL_STATUSES:
        return ClaimOutcome.FINISHED
    lease_live = job.lease_owner is not None and (
        job.lease_expires_at is not None and job.lease_expires_at >= now
    )
    if lease_live:
        return ClaimOutcome.LEASED
    if job.cancel_requested:
        _settle_unleased(session, job_id, now, "cancelled", error=None)
        return ClaimOutcome.CANCELLED
    _settle_unleased(
        session,
        job_id,
        now,
        "failed",
        error=f"gave up after {job.attempts} attempts"
        + (f"; last error: {job.error}" if job.error else ""),
    )
    return ClaimOutcome.EXHAUSTED


def _settle_unleased(
    session: Session, job_id: str, now: datetime, status: str, *, error: str | None
) -> bool:
    """End a job nobody holds (cancelled before start, or out of attempts)."""
    values: dict[str, Any] = {
        "status": status,
        "lease_owner": None,
        "lease_expires_at": None,
        "finished_at": now,
    }
    if error is not None:
        values["error"] = error
    done = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.status.in_(("queued", "running")), _lease_free(now))
        .values(**values)
        .execution_options(synchronize_session=False)
    ).rowcount
    session.commit()
    if done == 1:
        end_live_runs_of_ended_job(session, job_id, status, error)
    return done == 1


def cancelled_by(session: Session, job_id: str) -> str:
    """``cancelled by <email>``: who asked last to cancel ``job_id`` (the audit log's
    ``job.cancel``), or ``cancelled`` when nobody is on record."""
    email = session.scalar(
        select(AuditEntry.actor_email)
        .where(AuditEntry.action == "job.cancel", AuditEntry.target_id == job_id)
        .order_by(AuditEntry.id.desc())
        .limit(1)
    )
    return f"cancelled by {email}" if email else "cancelled"


def end_live_runs_of_ended_job(
    session: Session, job_id: str, status: str, error: str | None
) -> None:
    """A job just ended ``failed`` or ``cancelled``: end its live runs, if it is a live
    session's, keeping their rows and saying why (the error, or who cancelled it).
    Nothing for a job that succeeded (its handler ended the run) or of another kind."""
    if status == "failed":
        end_live_runs_of_job(session, job_id, error or "the job failed")
    elif status == "cancelled":
        end_live_runs_of_job(session, job_id, cancelled_by(session, job_id))


def heartbeat(session: Session, job_id: str, owner: str, lease_s: float) -> Heartbeat:
    """Extend the caller's lease; tell it whether it still holds it and if cancel was asked."""
    now = utcnow()
    held = session.execute(
        update(Job)
        .where(_held_by(job_id, owner), Job.lease_expires_at >= now)
        .values(heartbeat_at=now, lease_expires_at=now + timedelta(seconds=lease_s))
        .execution_options(synchronize_session=False)
    ).rowcount
    session.commit()
    cancel = session.scalar(select(Job.cancel_requested).where(Job.id == job_id))
    return Heartbeat(held=held == 1, cancel_requested=bool(cancel))


def update_job(session: Session, job_id: str, owner: str, **values: Any) -> bool:
    """Write progress fields (progress, steps_done, curve, checkpoint...) under the lease."""
    done = session.execute(
        update(Job)
        .where(_held_by(job_id, owner))
        .values(**values)
        .execution_options(synchronize_session=False)
    ).rowcount
    session.commit()
    return done == 1


def finish_job(
    session: Session,
    job_id: str,
    owner: str,
    status: str,
    *,
    result: dict[str, Any] | None = None,
    error: str | None = None,
    traceback: str | None = None,
    **values: Any,
) -> bool:
    """End the caller's job with a final status and release the lease."""
    if status not in JOB_FINAL_STATUSES:
        raise ValueError(f"{status!r} is not a final status {JOB_FINAL_STATUSES}")
    if status == "succeeded":
        values.setdefault("progress", 1.0)
    done = update_job(
        session,
        job_id,
        owner,
        status=status,
        result=result,
        error=error,
        traceback=traceback,
        lease_owner=None,
        lease_expires_at=None,
        finished_at=utcnow(),
        **values,
    )
    if done:
        end_live_runs_of_ended_job(session, job_id, status, error)
    return done


def release_for_retry(
    session: Session, job_id: str, owner: str, *, error: str, traceback: str | None
) -> str | None:
    """After a failed attempt: back to ``queued`` if attempts remain, else ``failed``.

    Returns the new status, or None if the caller no longer held the lease.
    """
    job = session.get(Job, job_id, populate_existing=True)
    if job is None or job.lease_owner != owner:
        return None
    if job.attempts >= job.max_attempts:
        done = finish_job(session, job_id, owner, "failed", error=error, traceback=traceback)
        return "failed" if done else None
    done = update_job(
        session,
        job_id,
        owner,
        status="queued",
        error=error,
        traceback=traceback,
        lease_owner=None,
        lease_expires_at=None,
    )
    return "queued" if done else None


def hand_back(session: Session, job_id: str, owner: str) -> bool:
    """A worker shutting down returns its job to the queue; the attempt does not count."""
    return update_job(
        session,
        job_id,
        owner,
        status="queued",
        lease_owner=None,
        lease_expires_at=None,
        attempts=Job.attempts - 1,  # >= 0: the caller claimed it
    )


def wait_for_children(session: Session, job_id: str, owner: str, **values: Any) -> bool:
    """Release a parent job's lease while its child jobs run (status stays ``running``)."""
    return update_job(
        session, job_id, owner, lease_owner=None, lease_expires_at=None, attempts=0, **values
    )


def children_status(session: Session, parent_id: str) -> dict[str, int]:
    """Number of child jobs of ``parent_id`` per status."""
    rows = session.execute(
        select(Job.status, func.count()).where(Job.parent_id == parent_id).group_by(Job.status)
    ).all()
    return {status: int(count) for status, count in rows}


def reap(session: Session, *, stale_queued_s: float | None = None) -> list[tuple[str, str]]:
    """The reaper: settle what dead workers left behind; returns ``(id, kind)`` to enqueue.

    * A ``running`` job whose lease expired goes back to ``queued`` (or to ``cancelled`` if
      cancel was asked, or ``failed`` if it has no attempts left) and is re-sent.
    * A waiting parent (``running``, no lease) gets its children's progress; once they are
      all final it is re-sent so it aggregates; if cancel was asked, its unfinished children
      are asked to cancel too.
    * With ``stale_queued_s``: a ``queued`` job untouched that long is re-sent (its message
      may have died with a worker before the claim); a duplicate is dropped by the claim.

    Every change is a conditional update, so several workers may reap at once.
    """
    now = utcnow()
    to_send: list[tuple[str, str]] = []
    expired = session.execute(
        select(Job.id, Job.kind, Job.cancel_requested, Job.attempts, Job.max_attempts).where(
            Job.status == "running",
            Job.lease_owner.is_not(None),
            Job.lease_expires_at < now,
        )
    ).all()
    for job_id, kind, cancel, attempts, max_attempts in expired:
        lost = and_(Job.id == job_id, Job.status == "running", Job.lease_expires_at < now)
        if cancel:
            values: dict[str, Any] = {"status": "cancelled", "finished_at": now}
        elif attempts >= max_attempts:
            values = {
                "status": "failed",
                "finished_at": now,
                "error": f"worker lost on the last of {max_attempts} attempts",
            }
        else:
            values = {"status": "queued"}
        done = session.execute(
            update(Job)
            .where(lost)
            .values(lease_owner=None, lease_expires_at=None, **values)
            .execution_options(synchronize_session=False)
        ).rowcount
        session.commit()
        if done == 1 and values["status"] == "queued":
            to_send.append((job_id, kind))
        elif done == 1:
            # no worker code runs to end a live session whose worker died: end it here
            end_live_runs_of_ended_job(session, job_id, values["status"], values.get("error"))

    waiting = session.execute(
        select(Job.id, Job.kind, Job.cancel_requested).where(
            Job.status == "running", Job.lease_owner.is_(None), Job.parent_id.is_(None)
        )
    ).all()
    for job_id, kind, cancel in waiting:
        _update_parent_progress(session, job_id)
        counts = children_status(session, job_id)
        unfinished = sum(n for status, n in counts.items() if status not in JOB_FINAL_STATUSES)
        if cancel and unfinished:
            cancel_children(session, job_id)
            counts = children_status(session, job_id)
            unfinished = sum(n for s, n in counts.items() if s not in JOB_FINAL_STATUSES)
        if not unfinished:
            to_send.append((job_id, kind))

    if stale_queued_s is not None:
        cutoff = now - timedelta(seconds=stale_queued_s)
        stale = session.execute(
            select(Job.id, Job.kind).where(Job.status == "queued", Job.updated_at < cutoff)
        ).all()
        for job_id, kind in stale:
            touched = session.execute(
                update(Job)
                .where(Job.id == job_id, Job.status == "queued", Job.updated_at < cutoff)
                .values(updated_at=now)
                .execution_options(synchronize_session=False)
            ).rowcount
            session.commit()
            if touched == 1:  # another worker's reaper did not send it first
                to_send.append((job_id, kind))
    return to_send


def child_weight(config: Any) -> int:
    """How much a child counts in its parent's progress: the runs its config lists
    (``runs``: a ``reproduce_batch`` holds several), else 1."""
    runs = config.get("runs") if isinstance(config, dict) else None
    return len(runs) if isinstance(runs, list) and runs else 1


def _update_parent_progress(session: Session, parent_id: str) -> None:
    """A waiting parent's progress: its children's, each weighted by :func:`child_weight`
    (the runs it holds), a final child counting as done."""
    rows = session.execute(
        select(Job.status, Job.progress, Job.config).where(Job.parent_id == parent_id)
    )
    shares = [
        (child_weight(config), 1.0 if status in JOB_FINAL_STATUSES else float(progress))
        for status, progress, config in rows
    ]
    if shares:
        total = sum(weight for weight, _ in shares)
        done = sum(weight * share for weight, share in shares)
        session.execute(
            update(Job)
            .where(Job.id == parent_id, Job.status == "running", Job.lease_owner.is_(None))
            .values(progress=min(done / total, 0.99))
            .execution_options(synchronize_session=False)
        )
        session.commit()


def cancel_children(session: Session, parent_id: str) -> int:
    """Ask every unfinished child to cancel; queued ones are cancelled at once."""
    now = utcnow()
    session.execute(
        update(Job)
        .where(Job.parent_id == parent_id, Job.status == "queued")
        .values(status="cancelled", cancel_requested=True, finished_at=now)
        .execution_options(synchronize_session=False)
    )
    asked = session.execute(
        update(Job)
        .where(Job.parent_id == parent_id, Job.status == "running")
        .values(cancel_requested=True)
        .execution_options(synchronize_session=False)
    ).rowcount
    session.commit()
    return int(asked)
