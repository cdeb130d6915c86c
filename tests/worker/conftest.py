"""A platform for worker tests: a migrated database, a broker, worker processes, job helpers."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import update
from sqlalchemy.orm import Session, sessionmaker

from services.core.db.migrate import upgrade_database
from services.core.db.models import Job
from services.core.db.session import make_engine, make_session_factory
from services.core.platform import PlatformSettings
from services.core.queue import enqueue_job, make_celery
from services.sim.maps import DEFAULT_MAP_PATH, load_map
from services.sim.oracle import Oracle
from services.sim.settings import SimSettings
from tests.helpers import env_without_bgrl, stop_processes

XDIST_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
"""This test process's name under pytest-xdist (``make test`` runs several); gw0 alone."""
_WORKER_INDEX = int(XDIST_WORKER.removeprefix("gw") or 0)
REDIS_URL = f"redis://127.0.0.1:6379/{11 + _WORKER_INDEX % 5}"
"""A Redis database of its own (11-15, one per test process), so other tests on this
machine's Redis, and the other test processes of the same run, are not disturbed."""
PG_ADMIN_URL = "host=127.0.0.1 port=5432 dbname=test user=postgres"
PG_DATABASE = f"bgrl_worker_test_{XDIST_WORKER}"
"""A PostgreSQL database of its own per test process, dropped and made anew per module."""


def pg_url(database: str = PG_DATABASE) -> str:
    return f"postgresql+psycopg://postgres@127.0.0.1:5432/{database}"


FAST_LEASE = {"BGRL_JOB_LEASE_S": "10", "BGRL_JOB_HEARTBEAT_S": "0.5"}
"""A dead worker's job is re-sent 10 s after its last heartbeat (30 s by default). Shorter
leases expire on a loaded test machine while a worker's first job imports and compiles
(the heartbeat thread waits for the GIL), which is safe (the job runs again) but slow."""
WORKER_TUNING = {"BGRL_REAPER_INTERVAL_S": "0.5", "BGRL_LOG_LEVEL": "INFO"}
TINY_PPO = {"n_epochs": 4, "eval_every": 256}
"""PPO overrides that keep test jobs short (seconds); results stay deterministic per seed."""


def redis_available() -> str | None:
    """None if Redis answers at 127.0.0.1:6379, else the reason to skip."""
    try:
        import redis

        redis.Redis.from_url(REDIS_URL, socket_connect_timeout=1).ping()
    except Exception as exc:
        return f"Redis at 127.0.0.1:6379 is not reachable ({type(exc).__name__})"
    return None


def postgres_database(database: str = PG_DATABASE) -> str | None:
    """(Re)create a PostgreSQL database of these tests (next to the shared ``test``, so
    other tests are not disturbed); None if done, else the reason to skip."""
    try:
        import psycopg

        with psycopg.connect(PG_ADMIN_URL, autocommit=True, connect_timeout=2) as conn:
            conn.execute(f"DROP DATABASE IF EXISTS {database} WITH (FORCE)")
            conn.execute(f"CREATE DATABASE {database}")
    except Exception as exc:
        return f"PostgreSQL at 127.0.0.1:5432 (db test, trust auth) is not usable ({exc})"
    return None


class Platform:
    """Database + broker + artifact store shared by the test and its worker processes."""

    def __init__(self, root: Path, env: dict[str, str]) -> None:
        self.root = root
        self.env = {"BGRL_DATA_DIR": str(root / "data"), **FAST_LEASE, **WORKER_TUNING, **env}
        fields = {
            "BGRL_DATA_DIR": "data_dir",
            "BGRL_DATABASE_URL": "database_url",
            "BGRL_BROKER_URL": "broker_url",
            "BGRL_ARTIFACT_DIR": "artifact_dir",
        }
        self.settings = PlatformSettings(
            **{field: self.env[var] for var, field in fields.items() if var in self.env}
        )
        upgrade_database(self.settings.resolved_database_url)
        self.engine = make_engine(self.settings.resolved_database_url)
        self.sessions: sessionmaker[Session] = make_session_factory(self.engine)
        self.celery = make_celery(self.settings)
        self.workers: list[subprocess.Popen[bytes]] = []
        self.logs: dict[int, Path] = {}

    def prewarm_oracle(self) -> None:
        """Build the default map's oracle lattice into the data folder's cache once, so
        worker processes load it (what a worker does on a host that ran jobs before)."""
        Oracle.clear_memory()
        cache_dir = SimSettings(data_dir=self.settings.data_dir).oracle_cache_dir
        Oracle.for_map(load_map(DEFAULT_MAP_PATH), cache_dir)

    def start_worker(
        self, name: str, env: dict[str, str] | None = None, cwd: Path | None = None
    ) -> subprocess.Popen[bytes]:
        """A ``bgrl worker`` process with the platform's environment (or exactly ``env``),
        no other ``BGRL_*`` setting of this process."""
        full_env = {**env_without_bgrl(), **(self.env if env is None else env)}
        log = self.root / f"worker-{name}.log"
        proc = subprocess.Popen(
            [sys.executable, "-m", "services.cli.main", "worker", "--name", name],
            cwd=cwd or self.root,
            env=full_env,
            stdout=log.open("wb"),
            stderr=subprocess.STDOUT,
        )
        self.workers.append(proc)
        self.logs[proc.pid] = log
        return proc

    def log(self, proc: subprocess.Popen[bytes]) -> str:
        return self.logs[proc.pid].read_text(errors="replace")

    def submit(self, kind: str, config: dict[str, Any], *, max_attempts: int = 3) -> str:
        """Commit a queued job row, then send its task (what the api does)."""
        with self.sessions() as session:
            job = Job(kind=kind, config=config, max_attempts=max_attempts)
            session.add(job)
            session.commit()
            job_id = job.id
        enqueue_job(self.celery, job_id, kind)
        return job_id

    def job(self, job_id: str) -> Job:
        with self.sessions() as session:
            job = session.get(Job, job_id)
            assert job is not None
            return job

    def set(self, job_id: str, **values: Any) -> None:
        with self.sessions() as session:
            session.execute(update(Job).where(Job.id == job_id).values(**values))
            session.commit()

    def wait(self, job_id: str, until: Any, timeout: float = 60.0, poll: float = 0.1) -> Job:
        """Poll the job row until ``until(job)`` is true (or its status is in ``until``)."""
        check = until if callable(until) else (lambda job: job.status in until)
        deadline = time.monotonic() + timeout
        while True:
            job = self.job(job_id)
            if check(job):
                return job
            if time.monotonic() > deadline:
                logs = "\n".join(p.read_text(errors="replace")[-3000:] for p in self.logs.values())
                raise AssertionError(
                    f"job {job_id} still {job.status} (error {job.error}) after {timeout} s\n{logs}"
                )
            time.sleep(poll)

    def close(self) -> None:
        stop_processes(self.workers)
        self.engine.dispose()


@pytest.fixture(scope="module")
def fs_platform(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Platform]:
    """The embedded platform: SQLite and the filesystem broker under one data folder."""
    platform = Platform(tmp_path_factory.mktemp("fs-platform"), {})
    platform.prewarm_oracle()
    try:
        yield platform
    finally:
        platform.close()
