"""Leases on job rows (services.core.db.jobs) on SQLite and PostgreSQL: one claim wins, a
lost lease is refused, the reaper settles what dead workers left, attempts are bounded."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import delete, update
from sqlalchemy.orm import Session, sessionmaker

from services.core.db import jobs as job_rows
from services.core.db.base import utcnow
from services.core.db.migrate import upgrade_database
from services.core.db.models import Job
from services.core.db.session import make_engine, make_session_factory
from tests.worker.conftest import XDIST_WORKER, pg_url, postgres_database

Claim = job_rows.ClaimOutcome


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def database(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[sessionmaker[Session]]:
    """A migrated database per backend, shared by this module's tests."""
    if request.param == "sqlite":
        url = f"sqlite:///{tmp_path_factory.mktemp('leases') / 'jobs.db'}"
    else:
        database_name = f"bgrl_worker_leases_{XDIST_WORKER}"
        reason = postgres_database(database_name)
        if reason:
            pytest.skip(reason)
        url = pg_url(database_name)
    upgrade_database(url)
    engine = make_engine(url)
    yield make_session_factory(engine)
    engine.dispose()


@pytest.fixture
def sessions(database: sessionmaker[Session]) -> sessionmaker[Session]:
    """The database with no job rows (the reaper looks at every row)."""
    with database() as session:
        session.execute(delete(Job).where(Job.parent_id.is_not(None)))
        session.execute(delete(Job))
        session.commit()
    return database


def add_job(sessions: sessionmaker[Session], **values: object) -> str:
    with sessions() as session:
        job = Job(**{"kind": "guided_ppo", "config": {}, **values})
        session.add(job)
        session.commit()
        return job.id


def row(sessions: sessionmaker[Session], job_id: str) -> Job:
    with sessions() as session:
        job = session.get(Job, job_id)
        assert job is not None
        return job


def expire(sessions: sessionmaker[Session], job_id: str) -> None:
    with sessions() as session:
        session.execute(
            update(Job)
            .where(Job.id == job_id)
            .values(lease_expires_at=utcnow() - timedelta(seconds=1))
        )
        session.commit()


def test_concurrent_claims_one_wins(sessions: sessionmaker[Session]) -> None:
    job_id = add_job(sessions)
    outcomes: list[Claim] = []
    barrier = threading.Barrier(8)

    def claim(i: int) -> None:
        with sessions() as session:
            barrier.wait()
            outcomes.append(job_rows.claim_job(session, job_id, f"w{i}", 30))

    threads = [threading.Thread(target=claim, args=(i,)) for i in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(o.value for o in outcomes) == ["claimed"] + ["leased"] * 7
    job = row(sessions, job_id)
    assert job.status == "running" and job.attempts == 1 and job.started_at is not None


def test_lost_lease_refuses_every_write(sessions: sessionmaker[Session]) -> None:
    job_id = add_job(sessions)
    with sessions() as session:
        assert job_rows.claim_job(session, job_id, "slow", 30) is Claim.CLAIMED
        assert job_rows.heartbeat(session, job_id, "slow", 30) == job_rows.Heartbeat(True, False)
    expire(sessions, job_id)  # "slow" paused past its lease; "fast" takes over
    with sessions() as session:
        assert job_rows.claim_job(session, job_id, "fast", 30) is Claim.CLAIMED
        assert job_rows.heartbeat(session, job_id, "slow", 30).held is False
        assert job_rows.update_job(session, job_id, "slow", progress=0.5) is False
        assert job_rows.finish_job(session, job_id, "slow", "succeeded") is False
        assert job_rows.update_job(session, job_id, "fast", progress=0.25) is True
    job = row(sessions, job_id)
    assert (job.lease_owner, job.attempts, job.progress, job.status) == ("fast", 2, 0.25, "running")


def test_cancel_request_is_seen_by_heartbeat_and_blocks_a_claim(
    sessions: sessionmaker[Session],
) -> None:
    running = add_job(sessions)
    queued = add_job(sessions, cancel_requested=True)
    with sessions() as session:
        job_rows.claim_job(session, running, "w", 30)
        session.execute(update(Job).where(Job.id == running).values(cancel_requested=True))
        session.commit()
        assert job_rows.heartbeat(session, running, "w", 30) == job_rows.Heartbeat(True, True)
        assert job_rows.claim_job(session, queued, "w", 30) is Claim.CANCELLED
    assert row(sessions, queued).status == "cancelled"


def test_retries_are_bounded_by_max_attempts(sessions: sessionmaker[Session]) -> None:
    job_id = add_job(sessions, max_attempts=2)
    with sessions() as session:
        for attempt, expected in ((1, "queued"), (2, "failed")):
            assert job_rows.claim_job(session, job_id, "w", 30) is Claim.CLAIMED
            status = job_rows.release_for_retry(
                session, job_id, "w", error=f"boom {attempt}", traceback="tb"
            )
            assert status == expected
        assert job_rows.claim_job(session, job_id, "w", 30) is Claim.FINISHED
    job = row(sessions, job_id)
    assert (job.status, job.attempts, job.error, job.lease_owner) == ("failed", 2, "boom 2", None)


def test_reaper_requeues_expired_leases_and_settles_the_rest(
    sessions: sessionmaker[Session],
) -> None:
    lost = add_job(sessions)
    lost_cancelled = add_job(sessions)
    lost_last_attempt = add_job(sessions, max_attempts=1)
    live = add_job(sessions)
    with sessions() as session:
        for job_id in (lost, lost_cancelled, lost_last_attempt, live):
            assert job_rows.claim_job(session, job_id, "w", 30) is Claim.CLAIMED
        session.execute(update(Job).where(Job.id == lost_cancelled).values(cancel_requested=True))
        session.commit()
    for job_id in (lost, lost_cancelled, lost_last_attempt):
        expire(sessions, job_id)
    with sessions() as session:
        assert job_rows.reap(session) == [(lost, "guided_ppo")]
        assert job_rows.reap(session) == []  # settled once
    assert [row(sessions, j).status for j in (lost, lost_cancelled, lost_last_attempt, live)] == [
        "queued",
        "cancelled",
        "failed",
        "running",
    ]
    assert row(sessions, lost_last_attempt).error == "worker lost on the last of 1 attempts"
    assert row(sessions, lost).lease_owner is None


def test_reaper_resends_stale_queued_jobs_and_finished_parents(
    sessions: sessionmaker[Session],
) -> None:
    stale = add_job(sessions)
    parent = add_job(sessions, kind="reproduce")
    with sessions() as session:
        session.execute(
            update(Job).where(Job.id == stale).values(updated_at=utcnow() - timedelta(seconds=100))
        )
        session.commit()
        assert job_rows.claim_job(session, parent, "w", 30) is Claim.CLAIMED
        assert job_rows.wait_for_children(session, parent, "w") is True
        done = Job(kind="reproduce_run", config={}, parent_id=parent, status="succeeded")
        pending = Job(kind="reproduce_run", config={}, parent_id=parent, progress=0.5)
        session.add_all([done, pending])
        session.commit()
        assert job_rows.reap(session, stale_queued_s=50) == [(stale, "guided_ppo")]
        assert row(sessions, parent).progress == 0.75  # (1 + 0.5) / 2
        session.execute(update(Job).where(Job.id == pending.id).values(status="failed"))
        session.commit()
        assert sorted(job_rows.reap(session, stale_queued_s=50)) == [(parent, "reproduce")]
        assert job_rows.claim_job(session, parent, "w2", 30) is Claim.CLAIMED
    assert row(sessions, parent).attempts == 1  # the wait gave the attempts back


def test_a_parents_progress_weighs_each_child_by_its_runs(
    sessions: sessionmaker[Session],
) -> None:
    parent = add_job(sessions, kind="reproduce")
    with sessions() as session:
        assert job_rows.claim_job(session, parent, "w", 30) is Claim.CLAIMED
        assert job_rows.wait_for_children(session, parent, "w") is True
        batch = Job(
            kind="reproduce_batch", config={"runs": [{}, {}, {}]}, parent_id=parent, progress=0.2
        )
        single = Job(kind="reproduce_run", config={}, parent_id=parent, status="succeeded")
        session.add_all([batch, single])
        session.commit()
        job_rows.reap(session)
    # (3 runs x 0.2 + 1 run x 1.0) / 4 runs; a plain mean of the children would be 0.6
    assert row(sessions, parent).progress == pytest.approx(0.4)


def test_hand_back_does_not_use_up_an_attempt(sessions: sessionmaker[Session]) -> None:
    job_id = add_job(sessions)
    with sessions() as session:
        assert job_rows.claim_job(session, job_id, "w", 30) is Claim.CLAIMED
        assert job_rows.hand_back(session, job_id, "w") is True
    job = row(sessions, job_id)
    assert (job.status, job.attempts, job.lease_owner) == ("queued", 0, None)


def test_a_dead_workers_untaken_messages_are_sent_again_at_once(tmp_path: Path) -> None:
    """A worker killed while holding a queued job's message (taken, not yet claimed) lost
    it; ``bgrl up``'s reaper sends every queued job again on the worker's exit instead of
    after ``stale_queued_s`` (the claim drops the duplicates)."""
    from services.core.platform import PlatformSettings
    from services.core.queue import make_celery
    from services.core.reaper import Reaper

    settings = PlatformSettings(data_dir=tmp_path)
    upgrade_database(settings.resolved_database_url)
    engine = make_engine(settings.resolved_database_url)
    sessions = make_session_factory(engine)
    try:
        queued = add_job(sessions)
        reaper = Reaper(sessions, make_celery(settings), interval_s=1, stale_queued_s=900)
        assert reaper.reap_once() == []  # queued a moment ago: not stale
        reaper.resend_queued_soon()
        assert reaper.reap_once() == [(queued, "guided_ppo")]
        assert reaper.reap_once() == []  # once
    finally:
        engine.dispose()
