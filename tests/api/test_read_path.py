"""The api's read path and its processes: the job list returns the job resource, every
request gives its database connection back, dead pooled PostgreSQL connections are replaced,
several api processes share one generated JWT key, and ``bgrl up`` starts the api with
``BGRL_API_WORKERS`` processes that do not migrate."""

from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.queues
import multiprocessing.synchronize
import os
import stat
import uuid
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import anyio.to_thread
import pytest
from sqlalchemy import Engine, text
from sqlalchemy.exc import OperationalError

from services.api.security import load_jwt_key
from services.api.settings import ApiSettings, default_api_workers
from services.cli.serve import SERVICES, _service_processes
from services.client import PlatformClient, PlatformError
from services.core.db import session as db_session
from services.core.db.session import make_engine
from services.core.settings import SettingsError
from tests.api.conftest import Api, make_settings, start_api
from tests.api.test_jobs import GUIDED, set_job, submit


def test_job_list_items_are_the_job_resource(api_any_db: Api) -> None:
    api = api_any_db
    job_id = submit(api, "guided_ppo", {**GUIDED, "seed": 3}).json()["id"]
    set_job(api, job_id, curve=[[0, 0.0], [2048, 0.5]], status="succeeded", progress=1.0)
    viewer = api.as_("viewer")
    page = api.client.get("/api/v1/jobs?limit=50", headers=viewer).json()
    one = api.client.get(f"/api/v1/jobs/{job_id}", headers=viewer).json()
    assert page["total"] == 1
    assert page["items"] == [one]
    assert one["status"] == "succeeded" and one["progress"] == 1.0
    assert "curve" not in one and "traceback" not in one


def test_every_request_gives_its_connection_back(api_any_db: Api) -> None:
    api = api_any_db
    staff = api.as_("staff")
    submit(api, "guided_ppo", {**GUIDED, "seed": 1})
    api.client.get("/api/v1/jobs", headers=staff)
    api.client.get("/api/v1/jobs/nope", headers=staff)
    api.client.get("/api/v1/jobs", headers={"Authorization": "Bearer bgrl_not-a-token"})
    api.client.post("/api/v1/subjects", json={"code": "S9"}, headers=staff)
    api.client.get("/healthz")
    assert api.client.app.state.engine.pool.checkedout() == 0  # type: ignore[attr-defined]


@pytest.mark.timeout(120)
def test_more_requests_than_connections_and_threads_do_not_deadlock(api: Api) -> None:
    """Each request keeps its connection across its thread hops (sign-in, then the route):
    with more requests in flight than the pool has connections and only a few threads,
    unadmitted requests would take every thread waiting for connections that requests
    between hops hold (until the pool's 30 s timeout, then a 500). Requests beyond the
    pool's capacity wait on the event loop instead, so every one is answered."""
    staff = api.as_("staff")
    portal = api.client.portal  # type: ignore[attr-defined]
    limiter = portal.call(anyio.to_thread.current_default_thread_limiter)
    threads = limiter.total_tokens
    portal.call(setattr, limiter, "total_tokens", 3)
    try:
        with ThreadPoolExecutor(max_workers=48) as pool:
            answers = list(
                pool.map(lambda _: api.client.get("/api/v1/jobs", headers=staff), range(96))
            )
    finally:
        portal.call(setattr, limiter, "total_tokens", threads)
    assert [answer.status_code for answer in answers] == [200] * 96
    assert api.client.app.state.engine.pool.checkedout() == 0  # type: ignore[attr-defined]


def _key_of(
    settings: ApiSettings,
    start: multiprocessing.synchronize.Barrier,
    keys: multiprocessing.queues.Queue[str],
) -> None:
    start.wait()
    keys.put(load_jwt_key(settings))


def test_concurrent_api_processes_generate_one_jwt_key(tmp_path: Path) -> None:
    settings = make_settings(tmp_path / "data", f"sqlite:///{tmp_path / 'bgrl.db'}")
    context = multiprocessing.get_context("fork")
    start, queue = context.Barrier(6), context.Queue()
    processes = [context.Process(target=_key_of, args=(settings, start, queue)) for _ in range(6)]
    for process in processes:
        process.start()
    keys = [queue.get(timeout=60) for _ in processes]
    for process in processes:
        process.join(timeout=60)
        assert process.exitcode == 0
    assert len(set(keys)) == 1 and len(keys[0]) == 64
    key_file = settings.api_dir / "jwt.key"
    assert stat.S_IMODE(key_file.stat().st_mode) == 0o600
    assert sorted(p.name for p in settings.api_dir.iterdir()) == ["jwt.key"]  # no drafts left


def test_up_starts_the_api_with_its_worker_processes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    api_spec = next(spec for spec in SERVICES if spec.name == "api")
    monkeypatch.setenv("BGRL_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("BGRL_API_WORKERS", "3")
    status = tmp_path / "processes.json"
    processes = _service_processes(api_spec, api_spec.load_settings(), 7, {}, status)
    # three supervised processes sharing the socket bgrl up bound (fd 7), none a grandchild
    assert [p.name for p in processes] == ["api-1", "api-2", "api-3"]
    assert all(p.pass_fds == (7,) and p.essential for p in processes)
    cmd = processes[0].cmd
    assert cmd[1:4] == ["-m", "services.cli.child", "services.api.app:app"]
    assert cmd[cmd.index("--fd") + 1] == "7"
    # each beats into its own file; a health check through the shared port proves nothing
    beats = [p.heartbeat_file for p in processes]
    assert beats == [tmp_path / f"api-{i}.beat" for i in (1, 2, 3)]
    assert all(p.cmd[p.cmd.index("--heartbeat") + 1] == str(p.heartbeat_file) for p in processes)
    assert all(p.health_url is None for p in processes)
    assert processes[0].env == {  # `bgrl up` migrated already
        "BGRL_MIGRATE_ON_START": "false",
        "BGRL_SUPERVISOR_STATUS_FILE": str(status),
    }
    monkeypatch.setenv("BGRL_API_WORKERS", "1")
    one = _service_processes(api_spec, api_spec.load_settings(), 7, {}, status)
    assert [p.name for p in one] == ["api"]
    assert one[0].health_url is not None and one[0].heartbeat_file == tmp_path / "api.beat"
    monkeypatch.setenv("BGRL_API_WORKERS", "0")
    with pytest.raises(SettingsError, match=r"invalid setting: BGRL_API_WORKERS \(got '0'\)"):
        api_spec.load_settings()


def test_default_api_workers_follow_the_cores_on_postgresql_and_are_one_on_sqlite() -> None:
    postgresql = {"database_url": "postgresql+psycopg://bgrl@db/bgrl"}
    assert default_api_workers(postgresql) == max(1, min(4, os.cpu_count() or 1))
    assert default_api_workers({"database_url": None}) == 1  # the embedded SQLite file
    assert default_api_workers({"database_url": "sqlite:////tmp/x.db"}) == 1
    assert ApiSettings(database_url=postgresql["database_url"]).api_workers == (
        default_api_workers(postgresql)
    )
    assert ApiSettings(database_url=None).api_workers == 1


def _backend_pid(engine: Engine) -> int:
    with engine.connect() as connection:
        return int(connection.scalar(text("SELECT pg_backend_pid()")))


def test_a_dead_pooled_connection_idle_long_enough_is_replaced(
    pg_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """PostgreSQL connections are pinged at checkout only after PING_AFTER_IDLE_S unused
    (no round trip per request under load): a connection the server dropped is then
    replaced unseen; one used just before is not pinged, so its query fails once and the
    pool is recycled (the server would have to restart within that second)."""
    engine = make_engine(pg_url)
    admin = make_engine(pg_url)
    try:
        for idle_s, fails_once in ((0.0, False), (3600.0, True)):
            monkeypatch.setattr(db_session, "PING_AFTER_IDLE_S", idle_s)
            pid = _backend_pid(engine)
            with admin.connect() as connection:
                connection.execute(text("SELECT pg_terminate_backend(:pid)"), {"pid": pid})
            if fails_once:
                with pytest.raises(OperationalError):
                    _backend_pid(engine)
            # the next connection is a new one, which works
            with engine.connect().execution_options(isolation_level="AUTOCOMMIT") as conn:
                assert conn.scalar(text("SELECT pg_backend_pid()")) != pid
            assert engine.pool.checkedout() == 0  # type: ignore[attr-defined]
    finally:
        engine.dispose()
        admin.dispose()


def test_a_request_that_finds_the_database_gone_is_a_503_a_client_read_waits_it_out(
    tmp_path: Path, pg_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """PostgreSQL restarting under the api: a request on a connection the server dropped
    is answered 503 with Retry-After (not a 500), the next one gets a new connection; the
    Python client sends a read answered so again after the wait, and only a read."""
    monkeypatch.setattr(db_session, "PING_AFTER_IDLE_S", 3600.0)  # no ping hides the drop
    name = f"bgrl_test_{uuid.uuid4().hex[:12]}"
    admin = make_engine(pg_url)

    def drop_the_api_connections() -> None:
        with admin.connect() as connection:
            dropped = connection.execute(text(
                "SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                "WHERE application_name = :name"), {"name": name}).all()  # fmt: skip
        assert dropped, "the api holds no connection"

    settings = make_settings(tmp_path, f"{pg_url}&application_name={name}")
    try:
        with contextlib.contextmanager(start_api)(settings) as api:
            staff = api.as_("staff")
            drop_the_api_connections()
            cut = api.client.get("/api/v1/jobs", headers=staff)
            assert cut.status_code == 503, cut.text
            assert cut.headers["Retry-After"] == "2" and "database" in cut.json()["detail"]
            assert api.client.get("/api/v1/jobs", headers=staff).status_code == 200

            client = PlatformClient("http://testserver", staff["Authorization"].split()[1])
            client._http = api.client  # the app in this process (TestClient is an httpx.Client)
            drop_the_api_connections()
            assert client.list_jobs().total == 0  # answered 503 once, then 200
            client.retry_s = 0.0
            drop_the_api_connections()
            with pytest.raises(PlatformError) as refused:
                client.list_jobs()
            assert refused.value.status == 503
            client.retry_s = 60.0
            assert client.list_jobs().total == 0  # a new connection
            drop_the_api_connections()
            with pytest.raises(PlatformError) as write:  # a write is never sent twice
                client.create_subject("S-503")
            assert write.value.status == 503
    finally:
        admin.dispose()
