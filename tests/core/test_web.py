"""The shared service skeleton: JSON errors for bad numbers, unknown fields and big bodies."""

from __future__ import annotations

import json
import logging
import os
import stat

import pytest
from fastapi import APIRouter, Query, WebSocket
from fastapi.testclient import TestClient
from pydantic_settings import SettingsConfigDict
from starlette.websockets import WebSocketDisconnect

from services.core.errors import NotFoundError
from services.core.files import write_json_atomic
from services.core.schemas import StrictRequest
from services.core.settings import BaseServiceSettings, SettingsError, load_settings
from services.core.web import create_service_app
from services.core.websockets import close_reason

router = APIRouter()


class Body(StrictRequest):
    x: float
    n: int = 0


@router.post("/echo")
def echo(body: Body) -> dict[str, float]:
    return {"x": body.x}


@router.get("/missing")
def missing() -> dict[str, str]:
    raise NotFoundError("no such thing", field="id")


@pytest.fixture
def client() -> TestClient:
    app = create_service_app(
        name="test", title="t", summary="t", version="0", max_body_size=100, routers=[router]
    )
    return TestClient(app)


@pytest.mark.parametrize(
    ("text", "field"),
    [('{"x": NaN}', "x"), ('{"x": 1e400}', "x"), ('{"x": 1, "n": Infinity}', "n")],
)
def test_non_finite_numbers_are_a_422_naming_the_field(client: TestClient, text, field) -> None:
    resp = client.post("/echo", content=text, headers={"content-type": "application/json"})
    assert resp.status_code == 422
    body = resp.json()
    assert body["detail"][0]["field"] == field
    assert body["message"].startswith(f"{field}:")


def test_unknown_field_is_refused(client: TestClient) -> None:
    resp = client.post("/echo", json={"x": 1, "typo": 2})
    assert resp.status_code == 422
    assert resp.json()["detail"][0]["field"] == "typo"


@pytest.mark.parametrize("text", ['{"x": 1,', "x=1", '{"x": 1} trailing'])
def test_a_body_that_is_not_json_names_the_body(client: TestClient, text: str) -> None:
    r = client.post("/echo", content=text, headers={"content-type": "application/json"})
    assert r.status_code == 422
    (entry,) = r.json()["detail"]
    assert entry["field"] == "body" and "input" not in entry
    assert entry["msg"].startswith("the body is not valid JSON: ")
    assert "(at character " in entry["msg"]


def test_close_reasons_fit_a_close_frame_without_splitting_a_character() -> None:
    assert close_reason("short") == "short"
    cut = close_reason("\u00e9" * 100)  # 200 bytes of UTF-8
    assert cut == "\u00e9" * 61 and len(cut.encode()) == 122


def test_over_limit_body_is_a_json_413(client: TestClient) -> None:
    declared = client.post("/echo", content=b"x" * 1000, headers={"content-type": "text/plain"})
    streamed = client.post(
        "/echo", content=(b"x" * 50 for _ in range(20)), headers={"content-type": "text/plain"}
    )
    for resp in (declared, streamed):
        assert resp.status_code == 413
        assert resp.headers["content-type"] == "application/json"
        assert "at most 100 bytes" in resp.json()["detail"]


def test_service_errors_and_request_ids(client: TestClient) -> None:
    resp = client.get("/missing", headers={"x-request-id": "abc123"})
    assert resp.status_code == 404
    assert resp.json() == {"detail": "no such thing", "field": "id"}
    assert resp.headers["x-request-id"] == "abc123"
    assert client.get("/health").json() == {"status": "ok", "service": "test"}
    assert len(client.get("/health").headers["x-request-id"]) == 16


def test_request_id_reaches_log_lines(client: TestClient, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.DEBUG, logger="bgrl.http"):
        client.get("/health", headers={"x-request-id": "rid-42"})
        client.get("/no-such-route", headers={"x-request-id": "rid-43"})
    lines = [r for r in caplog.records if r.name == "bgrl.http"]
    levels = {r.getMessage().split(" -> ")[0]: r.levelno for r in lines}
    # a passed health check (a supervisor's probe every few seconds) is not news
    assert levels == {"GET /health": logging.DEBUG, "GET /no-such-route": logging.INFO}


def test_settings_errors_are_one_line_naming_the_variable(monkeypatch) -> None:
    class DemoSettings(BaseServiceSettings):
        model_config = SettingsConfigDict(env_prefix="BGRL_DEMO_")

    monkeypatch.setenv("BGRL_DEMO_PORT", "abc")
    with pytest.raises(SettingsError) as info:
        load_settings(DemoSettings)
    message = str(info.value)
    assert "\n" not in message
    assert "BGRL_DEMO_PORT" in message and "'abc'" in message
    monkeypatch.setenv("BGRL_DEMO_PORT", "70000")
    with pytest.raises(SettingsError, match="BGRL_DEMO_PORT"):
        load_settings(DemoSettings)


def test_atomic_writes_get_the_mode_of_a_plain_write(tmp_path) -> None:
    old = os.umask(0o027)
    try:
        plain = tmp_path / "plain.json"
        plain.write_text("{}")
        atomic = write_json_atomic(tmp_path / "atomic.json", {})
    finally:
        os.umask(old)
    assert stat.S_IMODE(atomic.stat().st_mode) == stat.S_IMODE(plain.stat().st_mode) == 0o640


def test_atomic_json_refuses_nan_and_keeps_the_old_file(tmp_path) -> None:
    path = tmp_path / "a.json"
    write_json_atomic(path, {"a": 1})
    with pytest.raises(ValueError):
        write_json_atomic(path, {"a": float("nan")})
    assert json.loads(path.read_text()) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]


def test_service_token_guards_every_route_but_health() -> None:
    app = create_service_app(
        name="test",
        title="t",
        summary="t",
        version="0",
        max_body_size=100,
        routers=[router],
        service_token="s3cret-token-0123456789",
    )
    client = TestClient(app)
    assert client.get("/health").status_code == 200
    refused = client.post("/echo", json={"x": 1})
    assert refused.status_code == 401
    assert refused.json()["field"] == "x-service-token"
    wrong = client.post("/echo", json={"x": 1}, headers={"x-service-token": "nope"})
    assert wrong.status_code == 401
    ok = client.post("/echo", json={"x": 1}, headers={"x-service-token": "s3cret-token-0123456789"})
    assert ok.json() == {"x": 1.0}


def test_bad_websocket_query_closes_with_4422_naming_the_parameter() -> None:
    ws_router = APIRouter()

    @ws_router.websocket("/ws")
    async def ws(websocket: WebSocket, fps: float = Query(ge=1, le=30)) -> None:
        await websocket.accept()
        await websocket.close()

    app = create_service_app(
        name="t", title="t", summary="t", version="0", max_body_size=100, routers=[ws_router]
    )
    with TestClient(app).websocket_connect("/ws?fps=500") as socket:
        message = socket.receive_json()
        assert message["detail"][0]["field"] == "fps"
        with pytest.raises(WebSocketDisconnect) as info:
            socket.receive_json()
    assert info.value.code == 4422
