"""The closed loop on loopback: the sim, EEG and learner services as uvicorn processes
sharing one data folder and service token, and a worker runtime running jobs in this
process (no broker needed: the tests call the job runner directly)."""

from __future__ import annotations

import os
import signal
import subprocess
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest

from services.core.db.base import utcnow
from services.core.db.live import LiveRun, queue_live_job
from services.core.db.migrate import upgrade_database
from services.core.db.models import LabSession, Subject
from services.core.queue import make_celery
from services.platform.jobs import LIVE_SESSION
from services.sim.maps import DEFAULT_MAP_PATH, load_map
from services.sim.oracle import Oracle
from services.sim.settings import SimSettings
from services.worker.runtime import Runtime
from services.worker.settings import WorkerSettings
from tests.helpers import (
    INTERNAL_SERVICES,
    env_without_bgrl,
    free_port,
    start_service,
    stop_processes,
    wait_healthy,
)

TOKEN = "loop-test-token-0123456789"


class LoopPlatform:
    """Three services and a runtime; ``kill``/``start`` a service to test crashes."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.data_dir = root / "data"
        self.ports = {name: free_port() for name in INTERNAL_SERVICES}
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.env = {
            **env_without_bgrl(),
            "BGRL_DATA_DIR": str(self.data_dir),
            "BGRL_SERVICE_TOKEN": TOKEN,
            "BGRL_LOG_LEVEL": "WARNING",
        }
        for name, port in self.ports.items():
            os.environ[f"BGRL_{name.upper()}_URL"] = f"http://127.0.0.1:{port}"
        os.environ["BGRL_SERVICE_TOKEN"] = TOKEN
        os.environ["BGRL_LIVE_RETRY_S"] = "300"  # a restart takes long on a loaded machine
        settings = WorkerSettings(
            data_dir=self.data_dir, job_lease_s=30, job_heartbeat_s=0.5, service_token=TOKEN
        )
        upgrade_database(settings.resolved_database_url)
        self.runtime = Runtime(settings=settings, celery=make_celery(settings))
        Oracle.for_map(
            load_map(DEFAULT_MAP_PATH), SimSettings(data_dir=self.data_dir).oracle_cache_dir
        )

    def url(self, name: str) -> str:
        return f"http://127.0.0.1:{self.ports[name]}"

    def start(self, name: str) -> None:
        self.procs[name] = start_service(
            name, self.ports[name], env=self.env, cwd=self.root, log=self.root / f"{name}.log"
        )

    def wait_healthy(self, name: str, timeout: float = 90.0) -> None:
        wait_healthy(self.url(name), self.procs[name], self.root / f"{name}.log", timeout)

    def kill(self, name: str) -> None:
        proc = self.procs.pop(name)
        proc.send_signal(signal.SIGKILL)
        proc.wait()

    def close(self) -> None:
        stop_processes(self.procs.values(), timeout_s=10)
        self.runtime.engine.dispose()

    # ------------------------------------------------------------- rows
    def lab_session(self, kind: str, subject_code: str = "S-001") -> int:
        with self.runtime.sessions() as db:
            subject = db.query(Subject).filter_by(code=subject_code).one_or_none()
            if subject is None:
                subject = Subject(code=subject_code)
                db.add(subject)
                db.flush()
            start = utcnow()
            lab = LabSession(
                subject_id=subject.id, kind=kind, scheduled_at=start, duration_minutes=60,
                ends_at=start + timedelta(minutes=60),
            )  # fmt: skip
            db.add(lab)
            db.commit()
            return lab.id

    def live_job(self, session_id: int, options: dict[str, Any]) -> tuple[int, str]:
        """The rows ``POST /sessions/{id}/start`` writes: a live run and its queued job."""
        with self.runtime.sessions() as db:
            lab = db.get(LabSession, session_id)
            assert lab is not None
            run = LiveRun(session_id=session_id, mode=lab.kind, options=options, status="queued")
            db.add(run)
            db.flush()
            job = queue_live_job(db, run, LIVE_SESSION.name)
            db.commit()
            return run.id, job.id


@pytest.fixture(scope="module")
def loop(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LoopPlatform]:
    saved_env = dict(os.environ)  # the platform sets BGRL_* for its in-process runtime
    platform = LoopPlatform(tmp_path_factory.mktemp("loop"))
    try:
        for name in INTERNAL_SERVICES:
            platform.start(name)
        for name in INTERNAL_SERVICES:
            platform.wait_healthy(name)
        yield platform
    finally:
        platform.close()
        os.environ.clear()
        os.environ.update(saved_env)  # later tests must not inherit the service token
