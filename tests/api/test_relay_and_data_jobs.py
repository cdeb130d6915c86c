"""The frame relay's refusals (before any sim is contacted) and the data jobs' configs."""

from __future__ import annotations

from datetime import UTC, datetime

import pytest
from starlette.websockets import WebSocketDisconnect

from tests.api.conftest import Api


def _close_code(api: Api, path: str, token: str | None = None) -> int:
    protocols = ["bgrl", f"bearer.{token}"] if token else []
    with (
        pytest.raises(WebSocketDisconnect) as refused,
        api.client.websocket_connect(path, subprotocols=protocols) as ws,
    ):
        ws.receive_json()
    return refused.value.code


def test_frame_relay_checks_token_and_session_before_accept(api: Api) -> None:
    token = api.as_("viewer")["Authorization"].removeprefix("Bearer ")
    assert _close_code(api, "/api/v1/sessions/1/frames") == 4401
    assert _close_code(api, "/api/v1/sessions/1/frames", token="nope") == 4401
    assert _close_code(api, f"/api/v1/sessions/1/frames?token={token}") == 4401  # URLs are logged
    assert _close_code(api, "/api/v1/sessions/999/frames", token=token) == 4404


def test_frame_relay_accepts_then_closes_4404_while_a_session_has_no_sim_session(
    api: Api,
) -> None:
    """A signed-in page waiting for a session to start gets the close code (a handshake
    refused before ``accept`` reaches a browser only as 1006 and a console error)."""
    staff = api.as_("staff")
    subject = api.client.post("/api/v1/subjects", json={"code": "S-relay"}, headers=staff)
    body = {"subject_id": subject.json()["id"], "kind": "online",
            "scheduled_at": datetime.now(UTC).isoformat()}  # fmt: skip
    session = api.client.post("/api/v1/sessions", json=body, headers=staff).json()
    token = staff["Authorization"].removeprefix("Bearer ")
    path = f"/api/v1/sessions/{session['id']}/frames"
    # entered in order: a refused handshake would raise before pytest.raises is entered
    with (
        api.client.websocket_connect(path, subprotocols=["bgrl", f"bearer.{token}"]) as ws,
        pytest.raises(WebSocketDisconnect) as closed,
    ):
        ws.receive_json()
    assert closed.value.code == 4404 and "no running sim session" in closed.value.reason


def test_data_jobs_name_an_unknown_subject_or_session(api: Api) -> None:
    staff = api.as_("staff")
    for kind, config, name in (
        ("bids_export", {"subject_id": 77}, "config.subject_id"),
        ("session_replay", {"session_id": 77}, "config.session_id"),
    ):
        response = api.client.post(
            "/api/v1/jobs", json={"kind": kind, "config": config}, headers=staff
        )
        assert response.status_code == 422, response.text
        assert response.json()["field"] == name
    response = api.client.post(
        "/api/v1/jobs", json={"kind": "bids_export", "config": {"subject": 1}}, headers=staff
    )
    assert response.status_code == 422
