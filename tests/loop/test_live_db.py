"""Migration 0003 (live-session tables) from 0002 keeps the rows already there."""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

from sqlalchemy import inspect

from services.core.db.base import utcnow
from services.core.db.live import LiveMarker, LiveRun
from services.core.db.migrate import (
    current_revision,
    downgrade_database,
    head_revision,
    upgrade_database,
)
from services.core.db.models import LabSession, Subject
from services.core.db.session import make_engine, make_session_factory


def test_0002_upgrades_to_0003_keeping_rows_and_downgrades(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'bgrl.db'}"
    upgrade_database(url, "0002")
    engine = make_engine(url)
    try:
        sessions = make_session_factory(engine)
        with engine.begin() as connection:
            now = utcnow()
            connection.execute(Subject.__table__.insert().values(id=1, code="S-1", notes="",
                               created_at=now, updated_at=now))  # fmt: skip
            connection.execute(
                LabSession.__table__.insert().values(
                    id=1, subject_id=1, kind="online", scheduled_at=now, duration_minutes=60,
                    ends_at=now + timedelta(hours=1), status="scheduled", notes="",
                    created_at=now, updated_at=now,
                )
            )  # fmt: skip
        upgrade_database(url)
        assert current_revision(engine) == head_revision()
        with sessions() as db:
            lab = db.get(LabSession, 1)
            assert lab is not None and (lab.kind, lab.status) == ("online", "scheduled")
            run = LiveRun(session_id=1, mode="online", options={"label_budget": 5})
            db.add(run)
            db.flush()
            db.add(
                LiveMarker(run_id=run.id, session_id=1, step=0, sim_session_id="s", sim_step=0,
                           episode=0, action=2, oracle_correct=False, observation=[0.0] * 13,
                           marker_ts=1.0, eeg_ts=1.0, executed_at=now)
            )  # fmt: skip
            db.commit()
            assert (run.status, run.resumes, run.stop_requested) == ("queued", 0, False)
        downgrade_database(url, "0002")
        assert "live_runs" not in inspect(engine).get_table_names()
        with sessions() as db:
            assert db.get(LabSession, 1) is not None
    finally:
        engine.dispose()
