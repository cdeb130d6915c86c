"""Migrations (empty database and the previous revision), engines and the artifact store."""

from __future__ import annotations

import hashlib
from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import insert, inspect, select, text
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from services.core.artifacts import ArtifactStore
from services.core.db.base import Base
from services.core.db.live import LiveRun
from services.core.db.migrate import (
    current_revision,
    downgrade_database,
    head_revision,
    upgrade_database,
)
from services.core.db.models import Artifact, Job, LabSession, LoginAttempt, Subject, User
from services.core.db.session import make_engine, make_session_factory
from services.core.errors import BadRequestError, PayloadTooLargeError

TABLES = {
    "users",
    "api_tokens",
    "audit_log",
    "jobs",
    "artifacts",
    "rigs",
    "subjects",
    "sessions",
    "recordings",
    "classifiers",
    "hf_models",
    "feedback_labels",
    "live_runs",
    "live_markers",
    "live_decisions",
    "live_model_versions",
    "live_frames_shown",
    "login_attempts",
    "alembic_version",
}


def _add_user_at_an_old_revision(db: Session) -> int:
    """Insert a user naming only the columns every revision has (an ORM ``User(...)`` would
    name the later ones too); its id."""
    return db.scalar(
        insert(User).values(email="a@lab.test", password_hash="x", role="admin").returning(User.id)
    )


def test_empty_database_upgrades_to_head_matching_the_models(any_db_url: str) -> None:
    upgrade_database(any_db_url)
    engine = make_engine(any_db_url)
    try:
        assert current_revision(engine) == head_revision() == "0009"
        assert set(inspect(engine).get_table_names()) == TABLES
        with engine.connect() as connection:
            diff = compare_metadata(
                MigrationContext.configure(connection, opts={"compare_type": True}), Base.metadata
            )
        assert diff == []
    finally:
        engine.dispose()


def test_previous_revision_upgrades_and_keeps_its_rows(any_db_url: str) -> None:
    upgrade_database(any_db_url, "0001")
    engine = make_engine(any_db_url)
    try:
        assert current_revision(engine) == "0001"
        sessions = make_session_factory(engine)
        with sessions() as db:
            user_id = _add_user_at_an_old_revision(db)
            db.execute(  # the columns of revision 0001 only (as for the user)
                insert(Job).values(
                    id="j" * 32,
                    kind="guided_ppo",
                    config={"task": "sssg"},
                    status="queued",
                    progress=0.0,
                    attempts=0,
                    max_attempts=3,
                    steps_done=0,
                    curve=[],
                    cancel_requested=False,
                    submitter_id=user_id,
                    created_at=datetime(2026, 12, 1, tzinfo=UTC),
                    updated_at=datetime(2026, 12, 1, tzinfo=UTC),
                )
            )
            db.commit()
        upgrade_database(any_db_url)
        assert current_revision(engine) == "0009"
        with sessions() as db:
            job = db.get(Job, "j" * 32)
            assert (job.config, job.status, job.curve, job.attempts) == (
                {"task": "sssg"},
                "queued",
                [],
                0,
            )
        downgrade_database(any_db_url, "0001")
        assert "subjects" not in inspect(engine).get_table_names()
        downgrade_database(any_db_url, "base")
        assert set(inspect(engine).get_table_names()) == {"alembic_version"}
    finally:
        engine.dispose()


def test_revision_0003_upgrades_to_the_shared_login_limit_and_back(any_db_url: str) -> None:
    upgrade_database(any_db_url, "0003")
    engine = make_engine(any_db_url)
    try:
        sessions = make_session_factory(engine)
        with sessions() as db:
            _add_user_at_an_old_revision(db)
            db.commit()
        assert "login_attempts" not in inspect(engine).get_table_names()
        upgrade_database(any_db_url)
        assert current_revision(engine) == "0009"
        with sessions() as db:
            assert db.scalar(select(User.email)) == "a@lab.test"
            db.add(LoginAttempt(key="k" * 64, at=datetime(2026, 12, 2, tzinfo=UTC)))
            db.commit()
        downgrade_database(any_db_url, "0003")
        assert "login_attempts" not in inspect(engine).get_table_names()
        with sessions() as db:
            assert db.scalar(select(User.email)) == "a@lab.test"
    finally:
        engine.dispose()


def test_revision_0004_upgrades_to_live_runs_recording_their_method_and_back(
    any_db_url: str,
) -> None:
    upgrade_database(any_db_url, "0004")
    engine = make_engine(any_db_url)
    try:
        sessions = make_session_factory(engine)
        at = datetime(2026, 12, 2, tzinfo=UTC)
        with sessions() as db:
            subject = Subject(code="S01")
            db.add(subject)
            db.flush()
            lab = LabSession(
                subject_id=subject.id,
                kind="online",
                scheduled_at=at,
                duration_minutes=30,
                ends_at=at + timedelta(minutes=30),
            )
            db.add(lab)
            db.flush()
            db.execute(
                text(
                    "INSERT INTO live_runs (session_id, mode, options, status, stop_requested,"
                    " resumes, created_at, updated_at) VALUES (:s, 'online', :o, 'completed',"
                    " false, 0, :t, :t)"
                ),
                {"s": lab.id, "o": '{"seed": 3}', "t": at},
            )
            db.commit()
        upgrade_database(any_db_url)
        with sessions() as db:
            run = db.scalar(select(LiveRun))
            assert (run.options, run.status, run.hf_method) == ({"seed": 3}, "completed", None)
            run.hf_method = "categorical_kernel"
            db.commit()
        downgrade_database(any_db_url, "0004")
        columns = {c["name"] for c in inspect(engine).get_columns("live_runs")}
        assert "hf_method" not in columns and "options" in columns
        with engine.connect() as connection:
            assert connection.execute(text("SELECT count(*) FROM live_runs")).scalar() == 1
    finally:
        engine.dispose()


def test_constraints_and_utc_timestamps(any_db_url: str) -> None:
    upgrade_database(any_db_url)
    engine = make_engine(any_db_url)
    sessions = make_session_factory(engine)
    try:
        with sessions() as db:
            db.add(User(email="a@lab.test", password_hash="x", role="wizard"))
            with pytest.raises(IntegrityError):
                db.commit()
        with sessions() as db:
            db.add(Job(id="k" * 32, kind="guided_ppo", parent_id="missing" + "0" * 25))
            with pytest.raises(IntegrityError):
                db.commit()
        berlin = timezone(timedelta(hours=1))
        with sessions() as db:
            db.add(
                Job(
                    id="t" * 32,
                    kind="guided_ppo",
                    started_at=datetime(2026, 12, 7, 11, 0, tzinfo=berlin),
                )
            )
            db.commit()
        with sessions() as db:
            started = db.scalar(select(Job.started_at).where(Job.id == "t" * 32))
            assert started == datetime(2026, 12, 7, 10, 0, tzinfo=UTC)
            assert started.tzinfo is UTC
            naive = Job(id="n" * 32, kind="guided_ppo", started_at=datetime(2026, 12, 7))
            db.add(naive)
            with pytest.raises(Exception, match="naive datetime"):
                db.commit()
        expected = datetime(2026, 12, 7, 10, 0, tzinfo=UTC)
        with sessions() as db:  # a value in another zone is still read in UTC
            if engine.dialect.name == "postgresql":
                assert db.scalar(text("SHOW TIME ZONE")) == "UTC"  # every session's zone
                db.execute(text("SET TIME ZONE 'Asia/Kolkata'"))
            else:  # SQLite: text written by other means, with an offset
                db.execute(text("UPDATE jobs SET started_at = '2026-12-07 15:30:00+05:30'"))
            started = db.scalar(select(Job.started_at).where(Job.id == "t" * 32))
            assert started == expected and started.tzinfo is UTC
            db.rollback()
        with sessions() as db:  # a rolled-back transaction leaves the session in UTC
            if engine.dialect.name == "postgresql":
                assert db.scalar(text("SHOW TIME ZONE")) == "UTC"
    finally:
        engine.dispose()


def test_sqlite_engine_uses_wal_and_foreign_keys(tmp_path: Path) -> None:
    engine = make_engine(f"sqlite:///{tmp_path / 'sub' / 'x.db'}")
    try:
        with engine.connect() as connection:
            assert connection.execute(text("PRAGMA journal_mode")).scalar() == "wal"
            assert connection.execute(text("PRAGMA foreign_keys")).scalar() == 1
            assert connection.execute(text("PRAGMA busy_timeout")).scalar() == 10_000
    finally:
        engine.dispose()


def test_artifact_store_round_trip(tmp_path: Path) -> None:
    store = ArtifactStore(tmp_path / "store")
    source = tmp_path / "model.pt"
    source.write_bytes(b"weights" * 1000)
    stored = store.put_file(source, kind="model", name="../../policy final.pt")
    assert stored.sha256 == hashlib.sha256(b"weights" * 1000).hexdigest()
    assert stored.size_bytes == 7000
    assert stored.relpath.startswith("model/") and stored.relpath.endswith("/policy_final.pt")
    assert store.path(stored.relpath).read_bytes() == source.read_bytes()
    moved = store.put_file(source, kind="model", name="m.pt", move=True)
    assert not source.exists()
    assert moved.relpath != stored.relpath
    store.delete(stored.relpath)
    assert not store.path(stored.relpath).exists()
    assert not store.path(stored.relpath).parent.exists()
    with pytest.raises(BadRequestError, match="outside the artifact store"):
        store.path("../escape")
    with pytest.raises(BadRequestError, match="invalid artifact kind"):
        store.put_bytes(b"x", kind="../x", name="a")


def test_artifact_store_limit_leaves_nothing(tmp_path: Path) -> None:
    store = ArtifactStore(tmp_path / "store")
    with pytest.raises(PayloadTooLargeError):
        store.put_stream([b"a" * 10, b"b" * 10], kind="recording", name="r.bdf", max_bytes=15)
    assert [p for p in (tmp_path / "store").rglob("*") if p.is_file()] == []
    with pytest.raises(RuntimeError):
        store.put_stream(_failing_chunks(), kind="recording", name="r.bdf")
    assert [p for p in (tmp_path / "store").rglob("*") if p.is_file()] == []


def _failing_chunks():
    yield b"partial"
    raise RuntimeError("client went away")


def test_artifact_rows_reference_jobs(any_db_url: str) -> None:
    upgrade_database(any_db_url)
    engine = make_engine(any_db_url)
    try:
        with make_session_factory(engine)() as db:
            db.add(Job(id="p" * 32, kind="guided_ppo"))
            db.flush()
            db.add(
                Artifact(
                    id="a" * 32,
                    kind="checkpoint",
                    relpath="checkpoint/x/c.pt",
                    sha256="0" * 64,
                    size_bytes=1,
                    job_id="p" * 32,
                )
            )
            db.flush()
            db.get(Job, "p" * 32).checkpoint_artifact_id = "a" * 32
            db.commit()
            assert db.get(Job, "p" * 32).checkpoint_artifact_id == "a" * 32
    finally:
        engine.dispose()
