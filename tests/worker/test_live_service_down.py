"""A live session whose service stays down: each attempt but the last waits for it (the job
is retried and resumes from its rows); the last ends the session, keeps its rows, says so.
One whose worker died on the last attempt is ended likewise by the reaper."""

from __future__ import annotations

import time
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import func, select, update
from sqlalchemy.orm import Session, sessionmaker

from services.core.db import jobs as job_rows
from services.core.db.base import utcnow
from services.core.db.jobs import ClaimOutcome
from services.core.db.live import LiveMarker, LiveRun, queue_live_job
from services.core.db.migrate import upgrade_database
from services.core.db.models import AuditEntry, Job, LabSession, Subject
from services.core.db.session import make_engine, make_session_factory
from services.core.queue import make_celery
from services.platform.jobs import LIVE_SESSION
from services.worker.app import load_handler
from services.worker.runtime import JobContext, JobOutcome, Runtime, run_job
from services.worker.settings import WorkerSettings
from tests.helpers import free_port


@pytest.mark.parametrize("max_attempts", [1, 2])
def test_a_session_whose_service_stays_down_ends_on_the_last_attempt_keeping_its_rows(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, max_attempts: int
) -> None:
    dead = f"http://127.0.0.1:{free_port()}"  # nothing listens: the service is down
    for name in ("SIM", "EEG", "LEARNER"):
        monkeypatch.setenv(f"BGRL_{name}_URL", dead)
    monkeypatch.setenv("BGRL_LIVE_RETRY_S", "0.3")
    settings = WorkerSettings(data_dir=tmp_path, job_lease_s=30, job_heartbeat_s=0.5)
    upgrade_database(settings.resolved_database_url)
    runtime = Runtime(settings=settings, celery=make_celery(settings))
    with runtime.sessions() as db:
        subject = Subject(code="S-001")
        db.add(subject)
        db.flush()
        start = utcnow()
        lab = LabSession(
            subject_id=subject.id, kind="calibration", scheduled_at=start, duration_minutes=60,
            ends_at=start + timedelta(minutes=60),
        )  # fmt: skip
        db.add(lab)
        db.flush()
        run = LiveRun(session_id=lab.id, mode="calibration", options={}, status="queued")
        db.add(run)
        db.flush()
        job = queue_live_job(db, run, LIVE_SESSION.name, max_attempts=max_attempts)
        db.commit()
        run_id, lab_id, job_id = run.id, lab.id, job.id
    try:
        outcome = run_job(runtime, job_id, load_handler(LIVE_SESSION.name))
        with runtime.sessions() as db:
            job_row, run_row, lab_row = (
                db.get(Job, job_id), db.get(LiveRun, run_id), db.get(LabSession, lab_id)
            )  # fmt: skip
            assert job_row is not None and run_row is not None and lab_row is not None
            if max_attempts == 2:  # an attempt is left: the job waits for the service
                assert outcome == "queued"
                assert (run_row.status, lab_row.status) == ("running", "running")
                return
            assert outcome == "failed"
            assert job_row.status == "failed"
            assert f"the sim service at {dead} is unreachable" in (job_row.error or "")
            assert (run_row.status, lab_row.status) == ("failed", "failed")
            assert run_row.error is not None and run_row.error.startswith(
                f"session ended after 0 steps: the sim service at {dead} is unreachable"
            )
            assert run_row.error.endswith(
                "its markers, decisions and labels are kept, start the session again to resume"
            )
            assert run_row.finished_at is not None
    finally:
        runtime.engine.dispose()


@pytest.mark.parametrize("failed_by", ["reaper", "last attempt's error"])
def test_a_session_whose_job_fails_outside_its_loop_is_ended_keeping_its_rows(
    tmp_path: Path, failed_by: str
) -> None:
    """No live-session code runs to end it (its worker died on the last attempt, or the
    attempt raised): failing the job ends the run and its lab session with the reason, and
    the rows written so far stay."""
    url = f"sqlite:///{tmp_path / 'live.db'}"
    upgrade_database(url)
    engine = make_engine(url)
    sessions = make_session_factory(engine)
    try:
        run_id, lab_id, job_id = _running_session_with_one_step(sessions)
        with sessions() as db:
            assert job_rows.claim_job(db, job_id, "worker", 30) is ClaimOutcome.CLAIMED
        if failed_by == "reaper":
            with sessions() as db:
                db.execute(
                    update(Job)
                    .where(Job.id == job_id)
                    .values(lease_expires_at=utcnow() - timedelta(seconds=1))
                )
                db.commit()
            with sessions() as db:
                assert job_rows.reap(db) == []
            reason = "worker lost on the last of 1 attempts"
        else:
            reason = "RuntimeError: boom"
            with sessions() as db:
                status = job_rows.release_for_retry(
                    db, job_id, "worker", error=reason, traceback=None
                )
                assert status == "failed"
        with sessions() as db:
            job_row, run_row, lab_row = (
                db.get(Job, job_id), db.get(LiveRun, run_id), db.get(LabSession, lab_id)
            )  # fmt: skip
            assert job_row is not None and run_row is not None and lab_row is not None
            assert job_row.status == "failed"
            assert (run_row.status, lab_row.status) == ("failed", "failed")
            assert run_row.error == (
                f"session ended after 1 steps: {reason}; its markers, decisions and labels "
                "are kept, start the session again to resume"
            )
            assert run_row.finished_at is not None
            assert db.scalar(select(func.count()).where(LiveMarker.run_id == run_id)) == 1
    finally:
        engine.dispose()


def _running_session_with_one_step(sessions: sessionmaker[Session]) -> tuple[int, int, str]:
    """A running calibration session's live run with one step written, and its queued
    ``live_session`` job (one attempt): ``(run id, lab session id, job id)``."""
    with sessions() as db:
        subject = Subject(code="S-002")
        db.add(subject)
        db.flush()
        start = utcnow()
        lab = LabSession(
            subject_id=subject.id, kind="calibration", scheduled_at=start,
            duration_minutes=60, ends_at=start + timedelta(minutes=60), status="running",
        )  # fmt: skip
        db.add(lab)
        db.flush()
        run = LiveRun(session_id=lab.id, mode="calibration", options={}, status="running")
        db.add(run)
        db.flush()
        job = queue_live_job(db, run, LIVE_SESSION.name, max_attempts=1)
        db.flush()
        db.add(
            LiveMarker(
                run_id=run.id, session_id=lab.id, step=0, sim_session_id="sim-1", sim_step=0,
                episode=0, action=1, oracle_correct=True, observation=[0.0], marker_ts=1.0,
                eeg_ts=1.0, executed_at=start,
            )
        )  # fmt: skip
        db.commit()
        return run.id, lab.id, job.id


def _cancel_as_the_api_does(sessions: sessionmaker[Session], job_id: str, email: str) -> None:
    """What ``POST /jobs/{id}/cancel`` writes for a running job: the request and its audit."""
    with sessions() as db:
        db.execute(update(Job).where(Job.id == job_id).values(cancel_requested=True))
        db.add(AuditEntry(actor_email=email, action="job.cancel", target_type="job",
                          target_id=job_id))  # fmt: skip
        db.commit()


@pytest.mark.parametrize("ended_by", ["its worker", "the reaper", "the claim"])
def test_a_cancelled_session_ends_keeping_its_rows_and_says_who_cancelled_it(
    tmp_path: Path, ended_by: str
) -> None:
    """Cancel of a live session's job while a worker runs it (the worker ends the job), after
    its worker died (the reaper ends it when the lease expires), or before a worker claimed
    it again: the live run and its lab session end with ``cancelled by <email>``, rows kept."""
    url = f"sqlite:///{tmp_path / 'live.db'}"
    upgrade_database(url)
    settings = WorkerSettings(
        data_dir=tmp_path, database_url=url, job_lease_s=30, job_heartbeat_s=0.2
    )
    runtime = Runtime(settings=settings, celery=make_celery(settings))
    sessions = runtime.sessions
    try:
        run_id, lab_id, job_id = _running_session_with_one_step(sessions)
        if ended_by == "its worker":

            def handler(context: JobContext) -> JobOutcome:
                _cancel_as_the_api_does(sessions, job_id, "lab@example.org")
                deadline = time.monotonic() + 10
                while time.monotonic() < deadline:  # the loop's check between two actions
                    context.check_stop()
                    time.sleep(0.05)
                raise AssertionError("the cancel was not seen")

            assert run_job(runtime, job_id, handler) == "cancelled"
        elif ended_by == "the reaper":
            with sessions() as db:
                assert job_rows.claim_job(db, job_id, "dead-worker", 30) is ClaimOutcome.CLAIMED
            _cancel_as_the_api_does(sessions, job_id, "lab@example.org")
            with sessions() as db:
                db.execute(
                    update(Job)
                    .where(Job.id == job_id)
                    .values(lease_expires_at=utcnow() - timedelta(seconds=1))
                )
                db.commit()
            with sessions() as db:
                assert job_rows.reap(db) == []
        else:  # its worker died, then the reaper sent it again before the cancel
            _cancel_as_the_api_does(sessions, job_id, "lab@example.org")
            with sessions() as db:
                claim = job_rows.claim_job(db, job_id, "worker", 30)
                assert claim is ClaimOutcome.CANCELLED
        with sessions() as db:
            job_row, run_row, lab_row = (
                db.get(Job, job_id), db.get(LiveRun, run_id), db.get(LabSession, lab_id)
            )  # fmt: skip
            assert job_row is not None and run_row is not None and lab_row is not None
            assert job_row.status == "cancelled"
            assert (run_row.status, lab_row.status) == ("failed", "failed")
            assert run_row.error == (
                "session ended after 1 steps: cancelled by lab@example.org; its markers, "
                "decisions and labels are kept, start the session again to resume"
            )
            assert db.scalar(select(func.count()).where(LiveMarker.run_id == run_id)) == 1
    finally:
        runtime.engine.dispose()
