"""The audit's findings on the api, each closed: login timing, proxy headers, tokens in logs,
password-change guesses, abandoned upload parts, lone surrogates, API tokens minting tokens,
websockets outliving their token, file modes and 422s echoing secrets."""

from __future__ import annotations

import stat
import subprocess
import sys
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import httpx
import pytest
from argon2 import PasswordHasher
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from services.api import security
from services.api.app import create_app
from services.api.settings import ApiSettings
from services.core.artifacts import ArtifactStore
from tests.api.conftest import ADMIN_EMAIL, ADMIN_PASSWORD, PASSWORD, Api, make_settings
from tests.api.test_jobs import GUIDED, submit
from tests.helpers import env_without_bgrl, free_port, stop_processes, wait_healthy


class _CountingHasher(PasswordHasher):
    """argon2 at the tests' minimal cost, counting hashes and verifications."""

    def __init__(self) -> None:
        super().__init__(time_cost=1, memory_cost=64, parallelism=1)
        self.calls: list[str] = []

    def hash(self, password: str | bytes, *, salt: bytes | None = None) -> str:
        self.calls.append("hash")
        return super().hash(password, salt=salt)

    def verify(self, hash: str | bytes, password: str | bytes) -> bool:
        self.calls.append("verify")
        return super().verify(hash, password)


def test_a_login_costs_one_argon2_verification_whatever_the_account(
    api: Api, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Finding 2: an unknown e-mail hashed a dummy password on every login (731 vs 332 ms)."""
    hasher = _CountingHasher()
    monkeypatch.setattr(security, "_hasher", hasher)
    security.dummy_hash()  # what the api does at start-up, for its hasher
    hasher.calls.clear()
    for email, password in [
        ("nobody@lab.test", "whatever-password"),
        ("nobody-else@lab.test", "whatever-password"),
        (ADMIN_EMAIL, "wrong-password"),
        (ADMIN_EMAIL, ADMIN_PASSWORD),
    ]:
        api.client.post("/api/v1/auth/token", data={"username": email, "password": password})
        assert hasher.calls == ["verify"], email
        hasher.calls.clear()


def _api_process(tmp_path: Path) -> tuple[subprocess.Popen[bytes], str, Path]:
    """``bgrl up --only api`` (the launcher's options for uvicorn), its output in a file."""
    port = free_port()
    log = tmp_path / "api.log"
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli.main", "up", "--only", "api"],
        cwd=tmp_path,
        env={
            **env_without_bgrl(),
            "BGRL_DATA_DIR": str(tmp_path / "data"),
            "BGRL_ADMIN_EMAIL": ADMIN_EMAIL,
            "BGRL_ADMIN_PASSWORD": ADMIN_PASSWORD,
            "BGRL_LOGIN_MAX_FAILURES": "3",
            "BGRL_PORT": str(port),
        },
        stdout=log.open("ab"),
        stderr=subprocess.STDOUT,
    )
    url = f"http://127.0.0.1:{port}"
    wait_healthy(url, proc, log, timeout_s=180)
    return proc, url, log


def _fail_logins(url: str, n: int) -> list[int]:
    """``n`` wrong passwords for the admin, each claiming another client address."""
    return [
        httpx.post(
            f"{url}/api/v1/auth/token",
            data={"username": ADMIN_EMAIL, "password": "wrong-password"},
            headers={"X-Forwarded-For": f"203.0.113.{i + 1}"},
            timeout=30,
        ).status_code
        for i in range(n)
    ]


@pytest.mark.slow
def test_the_api_process_trusts_no_proxy_headers_logs_each_request_once_and_no_token(
    tmp_path: Path,
) -> None:
    """Findings 3 and 4, and issue 26's double log: from loopback, a new X-Forwarded-For per
    try bypassed the failed-login limit and put made-up addresses in the log; tokens in a
    websocket's URL went to the access log; uvicorn's access log repeated every request."""
    proc, url, log = _api_process(tmp_path)
    try:
        assert _fail_logins(url, 4) == [401, 401, 401, 429]
        secret = "bgrl_" + "s" * 43
        assert httpx.get(f"{url}/api/v1/users/me?token={secret}", timeout=30).status_code == 401
        ws_url = url.replace("http", "ws", 1) + f"/api/v1/jobs/x/events?token={secret}"
        with pytest.raises(InvalidStatus):
            connect(ws_url, open_timeout=30).close()
    finally:
        stop_processes([proc])
    text = log.read_text()
    assert secret not in text and "token=[redacted]" in text
    assert "203.0.113." not in text
    assert text.count("GET /api/v1/users/me") == 1, text


def test_launcher_options_for_proxies() -> None:
    assert ApiSettings().uvicorn_proxy_options() == ["--no-proxy-headers"]
    trusted = ApiSettings(trusted_proxies=["10.0.0.5", "10.1.0.0/16"])
    assert trusted.uvicorn_proxy_options() == [
        "--proxy-headers",
        "--forwarded-allow-ips",
        "10.0.0.5,10.1.0.0/16",
    ]
    with pytest.raises(ValueError, match="not an IP address"):
        ApiSettings(trusted_proxies=["proxy.lab"])


def test_access_log_lines_have_their_tokens_redacted() -> None:
    from services.core.logging import redact_secrets

    jwt = "eyJhbGciOiJIUzI1NiJ9.eyJzdWIiOiIxIn0.c2lnbmF0dXJl"
    line = f'127.0.0.1:5 - "WebSocket /api/v1/jobs/1/events?x=1&token={jwt}" 403'
    assert redact_secrets(line) == (
        '127.0.0.1:5 - "WebSocket /api/v1/jobs/1/events?x=1&token=[redacted]" 403'
    )
    assert redact_secrets(f"Authorization: Bearer {jwt}") == "Authorization: Bearer [redacted]"
    assert jwt not in redact_secrets(f"sent {jwt} and bgrl_{'a' * 40}")
    assert redact_secrets("GET /api/v1/tokens -> 200") == "GET /api/v1/tokens -> 200"


def test_current_password_guesses_are_limited(tmp_path: Path) -> None:
    """Finding 5: ``POST /users/me/password`` took unlimited current_password guesses."""
    settings = make_settings(
        tmp_path / "data", f"sqlite:///{tmp_path / 'db.sqlite'}", login_max_failures=3
    )
    with TestClient(create_app(settings)) as client:
        form = {"username": ADMIN_EMAIL, "password": ADMIN_PASSWORD}
        token = client.post("/api/v1/auth/token", data=form).json()["access_token"]
        headers = {"Authorization": f"Bearer {token}"}

        def change(current: str) -> httpx.Response:
            body = {"current_password": current, "new_password": "a-new-long-password"}
            return client.post("/api/v1/users/me/password", json=body, headers=headers)

        assert [change(f"guess-{i}").status_code for i in range(3)] == [422] * 3
        blocked = change(ADMIN_PASSWORD)  # even the right one waits
        assert blocked.status_code == 429
        assert blocked.json()["field"] == "current_password"
        assert 1 <= int(blocked.headers["retry-after"]) <= 300


def test_abandoned_upload_parts_are_removed_at_start_up(tmp_path: Path) -> None:
    """Finding 6: an api killed mid-upload left ``artifacts/.tmp/*.part`` forever; a part
    another api process is still writing stays."""
    settings = make_settings(tmp_path / "data", f"sqlite:///{tmp_path / 'db.sqlite'}")
    store = ArtifactStore(settings.resolved_artifact_dir)
    tmp = settings.resolved_artifact_dir / ".tmp"
    tmp.mkdir()
    (tmp / "0123abcd.part").write_bytes(b"x" * 4096)  # its writer was killed: no lock held

    def body() -> Iterator[bytes]:
        yield b"first"
        with TestClient(create_app(settings)):  # an api starting while this part is written
            parts = [p.name for p in tmp.iterdir()]
        assert len(parts) == 1 and parts[0] != "0123abcd.part"  # the live one stays
        yield b"second"

    stored = store.put_stream(body(), kind="recording", name="r.bdf")
    assert store.path(stored.relpath).read_bytes() == b"firstsecond"
    assert list(tmp.iterdir()) == []


def test_a_lone_surrogate_is_a_422(api: Api) -> None:
    """Finding 7: ``{"notes": "\\ud800"}`` gave a 500 text/plain (the 422 echoing it could
    not be encoded); in a free-form object it would have been stored."""
    staff = {**api.as_("staff"), "content-type": "application/json"}
    created = api.client.post(
        "/api/v1/subjects", content=b'{"code": "S-sur", "notes": "a\\ud800"}', headers=staff
    )
    assert created.status_code == 422
    assert created.headers["content-type"] == "application/json"
    assert [e["field"] for e in created.json()["detail"]] == ["notes"]
    assert api.client.get("/api/v1/subjects", headers=staff).json()["items"] == []
    job = api.client.post(
        "/api/v1/jobs",
        content=b'{"kind": "guided_ppo", "config": {"task": "SSSG", "\\udfff": 1}}',
        headers=staff,
    )
    assert job.status_code == 422
    assert "lone surrogate" in job.json()["message"]


def test_an_api_token_cannot_mint_api_tokens(api: Api) -> None:
    """Finding 8: a leaked API token could mint others that outlived its revocation."""
    created = api.client.post("/api/v1/tokens", json={"name": "s"}, headers=api.as_("staff"))
    script = {"Authorization": f"Bearer {created.json()['token']}"}
    minted = api.client.post("/api/v1/tokens", json={"name": "child"}, headers=script)
    assert minted.status_code == 403
    assert minted.json()["field"] == "token"
    listed = api.client.get("/api/v1/tokens", headers=api.as_("staff")).json()["items"]
    assert [t["name"] for t in listed] == ["s"]


def test_the_job_events_websocket_closes_when_its_token_is_revoked(api: Api) -> None:
    """Finding 9: an open job-events websocket kept pushing after its token's revocation."""
    job_id = submit(api, "guided_ppo", GUIDED).json()["id"]
    created = api.client.post("/api/v1/tokens", json={"name": "ws"}, headers=api.as_("viewer"))
    token = created.json()["token"]
    path = f"/api/v1/jobs/{job_id}/events"
    with api.client.websocket_connect(path, subprotocols=["bgrl", f"bearer.{token}"]) as ws:
        assert ws.receive_json()["status"] == "queued"
        revoked = api.client.delete(
            f"/api/v1/tokens/{created.json()['id']}", headers=api.as_("viewer")
        )
        assert revoked.status_code == 204
        started = time.monotonic()
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
        waited = time.monotonic() - started
    assert closed.value.code == 4401
    assert "revoked" in closed.value.reason
    assert waited < 5  # a generous bound: the check runs every 0.5 s


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_data_files_are_600_in_folders_of_700(tmp_path: Path) -> None:
    """Finding 10: ``bgrl.db`` and recordings were 644 in 755 folders."""
    data = tmp_path / "data"
    data.mkdir(mode=0o755)
    data.chmod(0o755)  # a folder from before the fix
    settings = make_settings(data, f"sqlite:///{data / 'bgrl.db'}", max_upload_bytes=1 << 20)
    with TestClient(create_app(settings)) as client:
        form = {"username": ADMIN_EMAIL, "password": ADMIN_PASSWORD}
        token = client.post("/api/v1/auth/token", data=form).json()["access_token"]
        headers = {"Authorization": f"Bearer {token}"}
        subject = client.post("/api/v1/subjects", json={"code": "S-m"}, headers=headers).json()
        body = {"subject_id": subject["id"], "kind": "calibration",
                "scheduled_at": datetime.now(UTC).isoformat()}  # fmt: skip
        session = client.post("/api/v1/sessions", json=body, headers=headers).json()
        uploaded = client.post(
            f"/api/v1/sessions/{session['id']}/recordings?filename=r.bdf",
            content=b"0" * 1000,
            headers=headers,
        )
        assert uploaded.status_code == 201, uploaded.text
    assert _mode(data) == 0o700
    assert _mode(data / "bgrl.db") == 0o600
    artifacts = settings.resolved_artifact_dir
    files = [p for p in artifacts.rglob("*") if p.is_file()]
    assert files, "the upload is stored"
    assert {_mode(p) for p in files} == {0o600}
    assert {_mode(p) for p in [artifacts, *artifacts.rglob("*")] if p.is_dir()} == {0o700}


def test_422_answers_never_echo_secrets(api: Api) -> None:
    """Finding 11: a 422 repeated the submitted input, passwords included."""
    admin = api.as_("admin")
    secret = "my-secret-password-123"
    answers = [
        api.client.post(
            "/api/v1/users",
            json={"email": "x@lab.test", "password": secret, "role": "chief"},
            headers=admin,
        ),
        api.client.post("/api/v1/users", json=["x@lab.test", secret], headers=admin),
        api.client.post(
            "/api/v1/users/me/password",
            json={"current_password": PASSWORD, "new_password": secret[:5]},
            headers=api.as_("viewer"),
        ),
        api.client.post("/api/v1/auth/token", data={"password": secret}),
    ]
    for answer in answers:
        assert answer.status_code == 422, answer.text
        assert secret not in answer.text and secret[:5] not in answer.text
    # a plain value of an ordinary field is still shown
    role = answers[0].json()["detail"]
    assert [e.get("input") for e in role if e["field"] == "role"] == ["chief"]
