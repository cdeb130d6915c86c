"""Bad input to the sim service: every bad number is a 422 naming the field, every bad
stream parameter a 4422 close naming it, a foreign Origin a 4403 before the handshake."""

from __future__ import annotations

import warnings
from collections.abc import Iterator

import pytest
from starlette.websockets import WebSocketDisconnect

from services.sim.app import create_app
from services.sim.settings import SimSettings

with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # starlette asks for httpx2; httpx works
    from fastapi.testclient import TestClient

BAD_NUMBERS = ["NaN", "Infinity", "-Infinity", "1e400"]


@pytest.fixture(scope="module")
def client() -> Iterator[TestClient]:
    with TestClient(create_app(SimSettings(lsl_markers=False, max_sessions=4))) as c:
        yield c


@pytest.fixture(scope="module")
def session_id(client: TestClient) -> str:
    response = client.post("/sessions", json={"seed": 0})
    assert response.status_code == 201, response.text
    return response.json()["id"]


def post_raw(client: TestClient, path: str, body: str):
    return client.post(path, content=body.encode(), headers={"content-type": "application/json"})


def assert_422_naming(response, field: str) -> None:
    assert response.status_code == 422, response.text
    assert response.headers["content-type"] == "application/json"
    body = response.json()  # parses: no bare NaN/Infinity echoed back
    assert [entry["field"] for entry in body["detail"]] == [field], body
    assert body["message"].startswith(f"{field}: ")


@pytest.mark.parametrize("number", BAD_NUMBERS)
@pytest.mark.parametrize(
    ("path", "template", "field"),
    [
        ("/sessions", '{{"seed": {}}}', "seed"),
        ("/sessions/{sid}/reset", '{{"seed": {}}}', "seed"),
        ("/sessions/{sid}/step", '{{"action": {}}}', "action"),
        ("/sessions/{sid}/paced", '{{"period_s": {}}}', "period_s"),
        ("/sessions/{sid}/paced", '{{"max_actions": {}}}', "max_actions"),
        ("/sessions/{sid}/paced/actions", '{{"actions": [0, {}]}}', "actions.1"),
    ],
)
def test_non_finite_numbers_are_422_naming_the_field(
    client: TestClient, session_id: str, number: str, path: str, template: str, field: str
) -> None:
    response = post_raw(client, path.format(sid=session_id), template.format(number))
    assert_422_naming(response, field)
    # nothing happened: the session is where it was, no paced mode, no queue
    state = client.get(f"/sessions/{session_id}").json()
    assert (state["step"], state["episode"], state["paced"]["running"]) == (0, 0, False)
    assert state["paced"]["queued_actions"] == 0


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ('{"seed": -1}', "seed"),
        ('{"seed": 1.5}', "seed"),
        ('{"seed": 9223372036854775808}', "seed"),  # 2^63: beyond what clients can carry
        ('{"seed": "3"}', "seed"),
    ],
)
def test_bad_seeds_are_422(client: TestClient, body: str, field: str) -> None:
    assert_422_naming(post_raw(client, "/sessions", body), field)
    assert client.get("/health").json()["sessions"] <= 1  # nothing was opened


def test_errors_name_their_field(client: TestClient, session_id: str) -> None:
    unknown = client.post("/sessions", json={"map": "atlantis"})
    assert unknown.status_code == 422 and unknown.json()["field"] == "map"
    queue = client.post(f"/sessions/{session_id}/paced/actions", json={"actions": [0] * 1000})
    assert queue.status_code == 200
    full = client.post(f"/sessions/{session_id}/paced/actions", json={"actions": [0]})
    assert full.status_code == 409 and full.json()["field"] == "actions"
    client.delete(f"/sessions/{session_id}/paced/actions")
    missing = client.get("/sessions/nope")
    assert missing.status_code == 404 and missing.json()["field"] is None
    assert missing.headers["x-request-id"]


def close_code_and_reason(client: TestClient, url: str, **kwargs) -> tuple[dict | None, int, str]:
    """First message (if any) and the close code and reason of a stream that is refused."""
    first = None
    with (
        pytest.raises(WebSocketDisconnect) as closed,
        client.websocket_connect(url, **kwargs) as ws,
    ):
        first = ws.receive_json()
        ws.receive_json()
    return first, closed.value.code, closed.value.reason


@pytest.mark.parametrize(
    ("query", "field"),
    [
        ("fps=0", "fps"),
        ("fps=31", "fps"),
        ("fps=nan", "fps"),
        ("fps=inf", "fps"),
        ("fps=fast", "fps"),
        ("view=side", "view"),
        ("encoding=hex", "encoding"),
        ("format=gif", "format"),
        ("on_action=maybe", "on_action"),
    ],
)
def test_bad_stream_parameters_close_4422_naming_them(
    client: TestClient, session_id: str, query: str, field: str
) -> None:
    first, code, reason = close_code_and_reason(client, f"/sessions/{session_id}/stream?{query}")
    assert code == 4422
    assert reason.startswith(f"{field}: ")
    assert first is not None and first["type"] == "error" and first["field"] == field


def test_stream_close_codes_differ(client: TestClient, session_id: str) -> None:
    with (
        pytest.raises(WebSocketDisconnect) as refused,
        client.websocket_connect(
            f"/sessions/{session_id}/stream?fps=0", headers={"origin": "http://evil.example"}
        ),
    ):
        pass  # refused before accept: the Origin is checked before anything else
    assert refused.value.code == 4403
    first, code, _ = close_code_and_reason(client, "/sessions/nope/stream")
    assert code == 4404 and first["type"] == "error" and "nope" in first["detail"]
    with client.websocket_connect(f"/sessions/{session_id}/stream?fps=30&view=topdown") as ws:
        assert ws.receive_json()["frame"]["view"] == "topdown"
