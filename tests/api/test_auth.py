"""Login, rate limit, API tokens, the JWT key, the first admin and account management."""

from __future__ import annotations

import logging
import stat
import subprocess
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from services.api.app import create_app
from services.core.db.models import LoginAttempt
from tests.api.conftest import ADMIN_EMAIL, ADMIN_PASSWORD, PASSWORD, Api, login, make_settings
from tests.helpers import env_without_bgrl, free_port, start_service, stop_processes, wait_healthy


def _token_form(email: str, password: str) -> dict[str, str]:
    return {"username": email, "password": password}


def test_login_issues_a_bearer_token(api: Api) -> None:
    response = api.client.post("/api/v1/auth/token", data=_token_form(ADMIN_EMAIL, ADMIN_PASSWORD))
    assert response.status_code == 200
    body = response.json()
    assert body["token_type"] == "bearer"
    me = api.client.get(
        "/api/v1/users/me", headers={"Authorization": f"Bearer {body['access_token']}"}
    )
    assert me.json()["email"] == ADMIN_EMAIL
    assert me.json()["role"] == "admin"


def test_wrong_password_is_401_naming_the_field(api: Api) -> None:
    response = api.client.post(
        "/api/v1/auth/token", data=_token_form(ADMIN_EMAIL, "wrong-password")
    )
    assert response.status_code == 401
    assert response.json() == {
        "detail": "wrong e-mail or password, or account deactivated",
        "field": "password",
    }
    missing = api.client.post("/api/v1/auth/token", data={"username": ADMIN_EMAIL})
    assert missing.status_code == 422
    assert missing.json()["detail"][0]["field"] == "password"


def test_failed_logins_are_rate_limited(tmp_path: Path) -> None:
    settings = make_settings(
        tmp_path / "data", f"sqlite:///{tmp_path / 'db.sqlite'}", login_max_failures=3
    )
    with TestClient(create_app(settings)) as client:
        for _ in range(3):
            response = client.post("/api/v1/auth/token", data=_token_form(ADMIN_EMAIL, "nope"))
            assert response.status_code == 401
        # even the right password waits until the window has passed
        blocked = client.post("/api/v1/auth/token", data=_token_form(ADMIN_EMAIL, ADMIN_PASSWORD))
        assert blocked.status_code == 429
        assert blocked.json()["field"] == "username"
        assert 1 <= int(blocked.headers["retry-after"]) <= 300
        # another account from the same address is not affected
        other = client.post("/api/v1/auth/token", data=_token_form("x@lab.test", "nope"))
        assert other.status_code == 401


def _login_status(client: TestClient, password: str) -> int:
    return client.post("/api/v1/auth/token", data=_token_form(ADMIN_EMAIL, password)).status_code


def test_two_api_instances_on_one_database_share_the_limit(tmp_path: Path, any_db_url: str) -> None:
    settings = make_settings(tmp_path / "data", any_db_url, login_max_failures=3)
    with TestClient(create_app(settings)) as one, TestClient(create_app(settings)) as two:
        assert one.app.state.engine is not two.app.state.engine
        assert [_login_status(one, "nope"), _login_status(two, "nope")] == [401, 401]
        # a success on either clears the key for both
        assert _login_status(two, ADMIN_PASSWORD) == 200
        statuses = [_login_status(c, "nope") for c in (one, two, one)]
        assert statuses == [401, 401, 401]
        assert _login_status(two, "nope") == 429
        blocked = one.post("/api/v1/auth/token", data=_token_form(ADMIN_EMAIL, ADMIN_PASSWORD))
        assert blocked.status_code == 429
        assert 1 <= int(blocked.headers["retry-after"]) <= 300
        with one.app.state.sessions() as db:
            assert db.scalar(select(func.count()).select_from(LoginAttempt)) == 3


@pytest.mark.slow
def test_two_uvicorn_processes_share_the_limit(tmp_path: Path, any_db_url: str) -> None:
    """Two api processes (replicas on two hosts, or ``BGRL_API_WORKERS``) on one database."""
    env = {
        **env_without_bgrl(),
        "BGRL_DATA_DIR": str(tmp_path / "data"),
        "BGRL_DATABASE_URL": any_db_url,
        "BGRL_ADMIN_EMAIL": ADMIN_EMAIL,
        "BGRL_ADMIN_PASSWORD": ADMIN_PASSWORD,
        "BGRL_EEG_URL": "",
        "BGRL_SIM_URL": "",
        "BGRL_LOGIN_MAX_FAILURES": "3",
    }
    processes: list[subprocess.Popen[bytes]] = []
    urls = []
    try:
        for i in range(2):  # one after the other: the first migrates and creates the admin
            port, log = free_port(), tmp_path / f"api-{i}.log"
            processes.append(start_service("api", port, env=env, cwd=tmp_path, log=log))
            urls.append(f"http://127.0.0.1:{port}")
            wait_healthy(urls[-1], processes[-1], log, path="/readyz")

        def status(url: str, password: str) -> int:
            form = _token_form(ADMIN_EMAIL, password)
            return httpx.post(f"{url}/api/v1/auth/token", data=form, timeout=30).status_code

        one, two = urls
        assert [status(one, "nope"), status(two, "nope"), status(one, "nope")] == [401] * 3
        assert [status(two, ADMIN_PASSWORD), status(one, ADMIN_PASSWORD)] == [429, 429]
    finally:
        stop_processes(processes)


def test_concurrent_failures_on_two_instances_are_counted_once_each(
    tmp_path: Path, any_db_url: str
) -> None:
    settings = make_settings(tmp_path / "data", any_db_url, login_max_failures=4)
    with TestClient(create_app(settings)) as one, TestClient(create_app(settings)) as two:
        clients = [one, two] * 8
        with ThreadPoolExecutor(max_workers=16) as pool:
            statuses = list(pool.map(lambda c: _login_status(c, "nope"), clients))
        assert sorted(statuses) == [401] * 4 + [429] * 12
        with one.app.state.sessions() as db:
            assert db.scalar(select(func.count()).select_from(LoginAttempt)) == 4


def test_window_slides_and_stale_attempts_are_pruned(tmp_path: Path) -> None:
    from datetime import timedelta

    from services.api.ratelimit import LoginLimiter, limit_key
    from services.core.db.base import utcnow
    from services.core.db.migrate import upgrade_database
    from services.core.db.session import make_engine, make_session_factory

    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    upgrade_database(url)
    engine = make_engine(url)
    now = [utcnow()]
    limiter = LoginLimiter(max_failures=2, window_s=60, clock=lambda: now[0])
    key, other = limit_key("10.0.0.1", "a@lab.test"), limit_key("10.0.0.2", "a@lab.test")
    try:
        with make_session_factory(engine)() as db:
            assert limiter.begin(db, other) == 0
            now[0] += timedelta(seconds=10)
            assert [limiter.begin(db, key) for _ in range(3)] == [0, 0, 60]
            now[0] += timedelta(seconds=59)
            assert limiter.begin(db, key) == 1  # both failures are still in the window
            now[0] += timedelta(seconds=1)
            assert limiter.begin(db, key) == 0  # they left it; this attempt is the only one
            assert db.scalars(select(LoginAttempt.key)).all() == [key]  # the rest pruned
            assert limiter.begin(db, key) == 0
            assert limiter.begin(db, key) == 60
    finally:
        engine.dispose()


def test_api_token_create_use_revoke(api: Api) -> None:
    created = api.client.post(
        "/api/v1/tokens", json={"name": "analysis script"}, headers=api.as_("staff")
    )
    assert created.status_code == 201
    body = created.json()
    token = body["token"]
    assert token.startswith("bgrl_")
    assert body["token_prefix"] == token[:12]
    assert body["expires_at"] is not None
    script = {"Authorization": f"Bearer {token}"}
    assert api.client.get("/api/v1/users/me", headers=script).json()["role"] == "staff"
    subject = api.client.post("/api/v1/subjects", json={"code": "S01"}, headers=script)
    assert subject.status_code == 201
    listed = api.client.get("/api/v1/tokens", headers=api.as_("staff")).json()
    assert [t["name"] for t in listed["items"]] == ["analysis script"]
    assert "token" not in listed["items"][0]
    assert listed["items"][0]["last_used_at"] is not None
    # another user cannot see or revoke it
    other = api.client.delete(f"/api/v1/tokens/{body['id']}", headers=api.as_("viewer"))
    assert other.status_code == 404
    revoked = api.client.delete(f"/api/v1/tokens/{body['id']}", headers=api.as_("staff"))
    assert revoked.status_code == 204
    refused = api.client.get("/api/v1/users/me", headers=script)
    assert refused.status_code == 401
    assert refused.json() == {"detail": "unknown or revoked API token", "field": "token"}


def test_api_token_expiry(api: Api) -> None:
    from datetime import timedelta

    from services.core.db.base import utcnow
    from services.core.db.models import ApiToken

    created = api.client.post(
        "/api/v1/tokens", json={"name": "short", "expires_in_days": 1}, headers=api.as_("viewer")
    ).json()
    with api.client.app.state.sessions() as db:
        db.get(ApiToken, created["id"]).expires_at = utcnow() - timedelta(seconds=1)
        db.commit()
    response = api.client.get(
        "/api/v1/users/me", headers={"Authorization": f"Bearer {created['token']}"}
    )
    assert response.status_code == 401
    assert response.json()["detail"] == "API token expired"
    bad = api.client.post(
        "/api/v1/tokens", json={"name": "x", "expires_in_days": 0}, headers=api.as_("viewer")
    )
    assert bad.status_code == 422
    assert bad.json()["detail"][0]["field"] == "expires_in_days"


def test_a_token_use_read_stale_by_several_requests_is_written_once(api_any_db: Api) -> None:
    """Requests that all read a token's last use as older than the resolution write it once:
    the later ones find it fresh and write nothing (no chain of commits on one row)."""
    from datetime import timedelta

    from services.api.deps import API_TOKEN_USE_RESOLUTION_S, API_TOKEN_USED
    from services.core.db.base import utcnow
    from services.core.db.models import ApiToken

    api = api_any_db
    created = api.client.post(
        "/api/v1/tokens", json={"name": "poller"}, headers=api.as_("viewer")
    ).json()
    now = utcnow()
    stale_before = now - timedelta(seconds=API_TOKEN_USE_RESOLUTION_S)
    sessions = api.client.app.state.sessions
    with sessions() as db:
        db.get(ApiToken, created["id"]).last_used_at = now - timedelta(hours=1)  # type: ignore[union-attr]
        db.commit()
    written = []
    for later in range(3):  # three requests that read the old time, one after the other
        with sessions() as db:
            params = {"token_id": created["id"], "stale_before": stale_before}
            at = now + timedelta(milliseconds=later)
            written.append(db.execute(API_TOKEN_USED, {**params, "now": at}).rowcount)
            db.commit()
    assert written == [1, 0, 0]
    with sessions() as db:
        assert db.get(ApiToken, created["id"]).last_used_at == now  # type: ignore[union-attr]
    response = api.client.get(
        "/api/v1/users/me", headers={"Authorization": f"Bearer {created['token']}"}
    )
    assert response.status_code == 200


def test_jwt_key_is_generated_once_with_mode_600(tmp_path: Path) -> None:
    settings = make_settings(tmp_path / "data", f"sqlite:///{tmp_path / 'db.sqlite'}")
    with TestClient(create_app(settings)) as client:
        headers = login(client, ADMIN_EMAIL, ADMIN_PASSWORD)
    key_file = tmp_path / "data" / "api" / "jwt.key"
    assert stat.S_IMODE(key_file.stat().st_mode) == 0o600
    key = key_file.read_text()
    # a restart keeps the key, so tokens issued before it stay valid
    with TestClient(create_app(settings)) as client:
        assert client.get("/api/v1/users/me", headers=headers).status_code == 200
    assert key_file.read_text() == key


def test_first_start_without_settings_creates_an_admin_and_logs_its_password_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    settings = make_settings(
        tmp_path / "data",
        f"sqlite:///{tmp_path / 'db.sqlite'}",
        admin_email=None,
        admin_password=None,
    )
    with (
        caplog.at_level(logging.WARNING, logger="services.api.accounts"),
        TestClient(create_app(settings)),
    ):
        pass
    lines = [r.getMessage() for r in caplog.records if "first start" in r.getMessage()]
    assert len(lines) == 1
    password = lines[0].split(" with password ")[1].split(" ")[0]
    with TestClient(create_app(settings)) as client:  # second start: nothing new
        headers = login(client, "admin@localhost", password)
        assert client.get("/api/v1/users/me", headers=headers).json()["role"] == "admin"
        users = client.get("/api/v1/users", headers=headers).json()
        assert users["total"] == 1
    assert len([r for r in caplog.records if "first start" in r.getMessage()]) == 1


def test_admin_manages_users_and_the_last_admin_stays(api: Api) -> None:
    admin = api.as_("admin")
    taken = api.client.post(
        "/api/v1/users", json={"email": "STAFF@lab.test", "password": PASSWORD}, headers=admin
    )
    assert taken.status_code == 409
    assert taken.json() == {"detail": "a user with e-mail staff@lab.test exists", "field": "email"}
    short = api.client.post(
        "/api/v1/users", json={"email": "new@lab.test", "password": "short"}, headers=admin
    )
    assert short.status_code == 422
    assert short.json()["detail"][0]["field"] == "password"
    last = api.client.patch(
        f"/api/v1/users/{api.user_ids['admin']}", json={"role": "staff"}, headers=admin
    )
    assert last.status_code == 409
    assert last.json() == {"detail": "this is the last active admin", "field": "role"}
    promoted = api.client.patch(
        f"/api/v1/users/{api.user_ids['staff']}", json={"role": "admin"}, headers=admin
    )
    assert promoted.json()["role"] == "admin"
    entries = api.client.get("/api/v1/audit?action=user.update", headers=admin).json()["items"]
    assert entries[0]["target_id"] == str(api.user_ids["staff"])
    assert entries[0]["detail"] == {"role": "admin"}
    assert entries[0]["actor_email"] == ADMIN_EMAIL


def test_change_own_password(api: Api) -> None:
    wrong = api.client.post(
        "/api/v1/users/me/password",
        json={"current_password": "not-it", "new_password": "another-long-password"},
        headers=api.as_("viewer"),
    )
    assert wrong.status_code == 422  # signed in: the field is wrong, not the token
    assert wrong.json()["field"] == "current_password"
    changed = api.client.post(
        "/api/v1/users/me/password",
        json={"current_password": PASSWORD, "new_password": "another-long-password"},
        headers=api.as_("viewer"),
    )
    assert changed.status_code == 204
    fresh = login(api.client, "viewer@lab.test", "another-long-password")
    assert api.client.get("/api/v1/users/me", headers=fresh).status_code == 200


def test_a_password_change_ends_the_access_tokens_issued_before(api: Api) -> None:
    """A password changed because it leaked must also end the sessions opened with it:
    access tokens issued before the change are refused (on a route that loads the user and
    on the job list), tokens issued after work, and API tokens (revoked one by one) stay."""
    email, old_password = "viewer@lab.test", PASSWORD
    second = login(api.client, email, old_password)  # e.g. another browser
    api_token = api.client.post("/api/v1/tokens", json={"name": "script"}, headers=second).json()[
        "token"
    ]
    changed = api.client.post(
        "/api/v1/users/me/password",
        json={"current_password": old_password, "new_password": "another-long-password"},
        headers=second,
    )
    assert changed.status_code == 204
    for stale in (api.as_("viewer"), second):
        for route in ("/api/v1/users/me", "/api/v1/jobs"):
            refused = api.client.get(route, headers=stale)
            assert refused.status_code == 401, route
            assert "before the password changed" in refused.json()["detail"]
    fresh = login(api.client, email, "another-long-password")
    assert api.client.get("/api/v1/users/me", headers=fresh).status_code == 200
    scripted = {"Authorization": f"Bearer {api_token}"}
    assert api.client.get("/api/v1/users/me", headers=scripted).status_code == 200

    # an admin setting the password ends them too
    reset = api.client.patch(
        f"/api/v1/users/{api.user_ids['viewer']}",
        json={"password": "a-third-long-password"},
        headers=api.as_("admin"),
    )
    assert reset.status_code == 200
    assert api.client.get("/api/v1/users/me", headers=fresh).status_code == 401
    assert api.client.get("/api/v1/users/me", headers=api.as_("admin")).status_code == 200
