"""Fixtures of the api tests: a migrated database (SQLite or PostgreSQL), the app, users."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, text

from services.api.app import create_app
from services.api.settings import ApiSettings
from tests.helpers import fast_password_hashing

PG_ADMIN_URLS = (
    "postgresql+psycopg://postgres@127.0.0.1:5432/test",
    "postgresql+psycopg://root@127.0.0.1:5432/test",
)
ADMIN_EMAIL = "admin@lab.test"
ADMIN_PASSWORD = "admin-password-123"
PASSWORD = "a-long-password-1"


def _postgres_admin_url() -> str | None:
    for url in PG_ADMIN_URLS:
        try:
            engine = create_engine(url, connect_args={"connect_timeout": 2})
            with engine.connect() as connection:
                connection.execute(text("SELECT 1"))
            engine.dispose()
            return url
        except Exception:
            continue
    return None


_PG_URL = _postgres_admin_url()


@pytest.fixture(autouse=True)
def _fast_password_hashing(monkeypatch: pytest.MonkeyPatch) -> None:
    fast_password_hashing(monkeypatch)


PG_SKIP_REASON = "no PostgreSQL at 127.0.0.1:5432 (database 'test', user postgres or root)"


@pytest.fixture(params=["sqlite", "postgresql"])
def any_db_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """An empty database: a SQLite file, or a fresh schema of PostgreSQL's ``test`` database."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'bgrl.db'}"
        return
    yield from _pg_schema_url()


@pytest.fixture
def pg_url() -> Iterator[str]:
    """An empty, private schema of PostgreSQL's ``test`` database (dropped afterwards)."""
    yield from _pg_schema_url()


def _pg_schema_url() -> Iterator[str]:
    if _PG_URL is None:
        pytest.skip(PG_SKIP_REASON)
    schema = f"bgrl_test_{uuid.uuid4().hex[:12]}"
    admin = create_engine(_PG_URL, isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(text(f'CREATE SCHEMA "{schema}"'))
    try:
        yield f"{_PG_URL}?options=-csearch_path%3D{schema}"
    finally:
        with admin.connect() as connection:
            connection.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
        admin.dispose()


def make_settings(data_dir: Path, database_url: str, **overrides: Any) -> ApiSettings:
    """Api settings for a test: its own data folder, database, embedded broker, no EEG."""
    values: dict[str, Any] = {
        "data_dir": data_dir,
        "database_url": database_url,
        "broker_url": None,
        "admin_email": ADMIN_EMAIL,
        "admin_password": ADMIN_PASSWORD,
        "eeg_url": None,
        "max_upload_bytes": 64 * 1024,
        **overrides,
    }
    return ApiSettings(**values)


@dataclass
class Api:
    """A running app, its settings and a bearer header per role."""

    client: TestClient
    settings: ApiSettings
    headers: dict[str, dict[str, str]]
    user_ids: dict[str, int]

    def as_(self, role: str) -> dict[str, str]:
        return self.headers[role]


def login(client: TestClient, email: str, password: str) -> dict[str, str]:
    """Bearer header of a fresh access token."""
    response = client.post("/api/v1/auth/token", data={"username": email, "password": password})
    assert response.status_code == 200, response.text
    return {"Authorization": f"Bearer {response.json()['access_token']}"}


def start_api(settings: ApiSettings, **app_kwargs: Any) -> Iterator[Api]:
    """The app with an admin (from settings), a staff and a viewer account signed in."""
    with TestClient(create_app(settings, **app_kwargs)) as client:
        admin = login(client, ADMIN_EMAIL, ADMIN_PASSWORD)
        headers = {"admin": admin}
        user_ids = {"admin": client.get("/api/v1/users/me", headers=admin).json()["id"]}
        for role in ("staff", "viewer"):
            email = f"{role}@lab.test"
            created = client.post(
                "/api/v1/users",
                json={"email": email, "password": PASSWORD, "role": role},
                headers=admin,
            )
            assert created.status_code == 201, created.text
            user_ids[role] = created.json()["id"]
            headers[role] = login(client, email, PASSWORD)
        yield Api(client, settings, headers, user_ids)


def calibration_session(api: Api) -> int:
    """Id of a new calibration session of a new subject ``S01`` (created by staff)."""
    staff = api.as_("staff")
    subject = api.client.post("/api/v1/subjects", json={"code": "S01"}, headers=staff)
    session = api.client.post(
        "/api/v1/sessions",
        json={
            "subject_id": subject.json()["id"],
            "kind": "calibration",
            "scheduled_at": "2037-12-07T10:00:00Z",
        },
        headers=staff,
    )
    return session.json()["id"]


@pytest.fixture
def api(tmp_path: Path) -> Iterator[Api]:
    """The app on a SQLite database."""
    yield from start_api(make_settings(tmp_path / "data", f"sqlite:///{tmp_path / 'bgrl.db'}"))


@pytest.fixture
def api_any_db(tmp_path: Path, any_db_url: str) -> Iterator[Api]:
    """The app on SQLite and on PostgreSQL."""
    yield from start_api(make_settings(tmp_path / "data", any_db_url))
