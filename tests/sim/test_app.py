"""The sim service over HTTP and websocket (Starlette test client, no network, no LSL)."""

from __future__ import annotations

import base64
import io
import time
import warnings
from collections.abc import Iterator

import numpy as np
import pytest
from PIL import Image
from starlette.websockets import WebSocketDisconnect

from services.core.actions import Action
from services.sim.app import create_app
from services.sim.env import BrainNavEnv
from services.sim.maps import DEFAULT_MAP_PATH, MAPS_DIR, load_map
from services.sim.settings import SimSettings

with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # starlette asks for httpx2; httpx works
    from fastapi.testclient import TestClient

JPEG_MAGIC = b"\xff\xd8\xff"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def make_client(**overrides: object) -> TestClient:
    settings = SimSettings(lsl_markers=False, **overrides)
    return TestClient(create_app(settings))


@pytest.fixture
def client() -> Iterator[TestClient]:
    with make_client(max_sessions=3, allowed_origins=["http://dashboard.example"]) as c:
        yield c


def open_session(client: TestClient, **body: object) -> dict:
    response = client.post("/sessions", json={"seed": 0, **body})
    assert response.status_code == 201, response.text
    return response.json()


def wait_for(predicate, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        time.sleep(0.02)


def test_settings_validate_frame_rate(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("BGRL_SIM_FRAME_RATE_FPS", "45")
    with pytest.raises(ValueError, match="frame_rate_fps"):
        SimSettings()
    monkeypatch.setenv("BGRL_SIM_FRAME_RATE_FPS", "10")
    settings = SimSettings()
    assert settings.frame_rate_fps == 10
    assert settings.port == 8001
    assert settings.paced_action_period_s == 1.5


def test_health_and_maps(client: TestClient) -> None:
    health = client.get("/health").json()
    assert health["status"] == "ok"
    assert health["sessions"] == 0
    assert health["lsl_markers"] is False
    maps = {m["name"]: m for m in client.get("/maps").json()}
    shipped = sorted(p.stem for p in MAPS_DIR.glob("*.json"))
    assert sorted(maps) == shipped  # default, open and the six map-study candidates
    assert [name for name, m in maps.items() if m["default"]] == ["default"]
    assert maps["default"]["description"] == load_map(DEFAULT_MAP_PATH).description
    assert maps["candidate_pocket"]["description"].startswith("Map study")
    paths = client.get("/openapi.json").json()["paths"]
    assert "/sessions/{session_id}/step" in paths and "/sessions/{session_id}/paced" in paths


def test_session_lifecycle(client: TestClient) -> None:
    session = open_session(client, task="vssg", reward_mode="rich")
    sid = session["id"]
    assert session["task"] == "vssg" and session["reward_mode"] == "rich"
    assert session["map"] == "default"
    assert session["episode"] == 0 and session["step"] == 0
    assert len(session["observation"]) == 13
    assert session["info"]["shortest_path_steps"] > 0
    assert [s["id"] for s in client.get("/sessions").json()] == [sid]

    oracle_before = client.get(f"/sessions/{sid}/oracle").json()
    step = client.post(f"/sessions/{sid}/step", json={"action": Action.TURN_LEFT}).json()
    marker = step["marker"]
    assert marker["session_id"] == sid
    assert (marker["step"], marker["episode"], marker["action"]) == (0, 0, Action.TURN_LEFT)
    assert marker["correct"] == (Action.TURN_LEFT in oracle_before["optimal_actions"])
    assert step["timestamp"] == marker["timestamp"]
    assert step["reward"] < -1.0  # rich reward adds distance and heading penalties
    assert step["info"]["pose"][2] != pytest.approx(session["pose"][2])

    state = client.get(f"/sessions/{sid}").json()
    assert state["step"] == 1 and state["episode_step"] == 1
    assert state["last_marker"] == marker

    reset = client.post(f"/sessions/{sid}/reset", json={"seed": 3}).json()
    assert reset["episode"] == 1
    assert reset["info"]["shortest_path_steps"] > 0
    second = client.post(f"/sessions/{sid}/step", json={"action": 0}).json()["marker"]
    assert (second["step"], second["episode"]) == (1, 1)
    assert client.get(f"/sessions/{sid}/markers").json() == [marker, second]
    assert client.get(f"/sessions/{sid}/markers", params={"since_step": 1}).json() == [second]

    assert client.delete(f"/sessions/{sid}").status_code == 204
    for method, path, body in [
        ("GET", f"/sessions/{sid}", None),
        ("POST", f"/sessions/{sid}/step", {"action": 0}),
        ("POST", f"/sessions/{sid}/reset", {}),
        ("DELETE", f"/sessions/{sid}", None),
    ]:
        response = client.request(method, path, json=body)
        assert response.status_code == 410, (method, path)
        assert "closed" in response.json()["detail"]
    assert client.get("/sessions").json() == []


def test_http_trajectory_matches_direct_env(client: TestClient) -> None:
    actions = [0, 1, 0, 0, 2, 0, 1, 1, 0]
    session = open_session(client, task="vssg", seed=7)
    env = BrainNavEnv(task="vssg")
    try:
        obs, _ = env.reset(seed=7)
        assert session["observation"] == pytest.approx(obs.tolist())
        for action in actions:
            step = client.post(f"/sessions/{session['id']}/step", json={"action": action}).json()
            obs, reward, terminated, _, _ = env.step(action)
            assert step["observation"] == pytest.approx(obs.tolist())
            assert step["reward"] == pytest.approx(reward)
            if terminated:
                break
    finally:
        env.close()


def test_oracle_policy_over_http_reaches_goal_in_shortest_path_steps(client: TestClient) -> None:
    session = open_session(client)
    sid = session["id"]
    expected = session["info"]["shortest_path_steps"]
    assert client.get(f"/sessions/{sid}/oracle").json()["cost_to_go"] == expected
    taken = 0
    while taken < expected + 5:
        optimal = client.get(f"/sessions/{sid}/oracle").json()["optimal_actions"]
        action = Action.FORWARD if Action.FORWARD in optimal else min(optimal)
        step = client.post(f"/sessions/{sid}/step", json={"action": action}).json()
        taken += 1
        assert step["marker"]["correct"] is True
        if step["terminated"]:
            break
    assert step["info"]["is_success"] is True
    assert taken == expected


def test_oracle_at_explicit_pose(client: TestClient) -> None:
    sid = open_session(client)["id"]
    here = client.get(f"/sessions/{sid}/oracle").json()
    x, y, yaw = here["pose"]
    there = client.get(f"/sessions/{sid}/oracle", params={"x": x, "y": y, "yaw": yaw}).json()
    assert there == here
    in_wall = client.get(f"/sessions/{sid}/oracle", params={"x": 0.1, "y": 6, "yaw": 0}).json()
    assert in_wall["reachable"] is False and in_wall["cost_to_go"] is None
    assert in_wall["optimal_actions"] == []
    partial = client.get(f"/sessions/{sid}/oracle", params={"x": 1.0})
    assert partial.status_code == 422
    assert partial.json() == {
        "detail": "give all of x, y and yaw, or none for the robot's pose",
        "field": "y",
    }


@pytest.mark.parametrize(
    ("params", "field"),
    [
        ({"x": 1e308, "y": 6, "yaw": 0}, "x"),  # a 500 (overflow) before
        ({"x": 2, "y": -1e308, "yaw": 0}, "y"),
        ({"x": -50, "y": 6, "yaw": 0}, "x"),  # off the floor
        ({"x": 2, "y": 12.01, "yaw": 0}, "y"),
        ({"x": 2, "y": 6, "yaw": 1e308}, "yaw"),
        ({"x": "nan", "y": 6, "yaw": 0}, "x"),
        ({"x": 2, "y": "inf", "yaw": 0}, "y"),
        ({"x": 2, "y": 6, "yaw": "-Infinity"}, "yaw"),
        ({"x": 2, "y": 6, "yaw": "NaN"}, "yaw"),
    ],
)
def test_oracle_query_numbers_must_be_finite_and_on_the_map(
    client: TestClient, params: dict, field: str
) -> None:
    sid = open_session(client)["id"]
    response = client.get(f"/sessions/{sid}/oracle", params=params)
    assert response.status_code == 422, response.text
    body = response.json()
    fields = [e["field"] for e in body["detail"]] if isinstance(body["detail"], list) else []
    assert body.get("field") == field or fields == [field], body


def test_bad_requests_get_clear_4xx(client: TestClient) -> None:
    assert client.get("/sessions/nope").status_code == 404
    assert "nope" in client.get("/sessions/nope").json()["detail"]
    assert client.post("/sessions/nope/step", json={"action": 0}).status_code == 404

    unknown_map = client.post("/sessions", json={"map": "atlantis"})
    assert unknown_map.status_code == 422
    assert "atlantis" in unknown_map.json()["detail"] and "default" in unknown_map.json()["detail"]
    outside_path = client.post("/sessions", json={"map": "/etc/passwd"})
    assert outside_path.status_code == 422
    assert client.post("/sessions", json={"task": "maze"}).status_code == 422
    assert client.post("/sessions", json={"reward_mode": "geodesic"}).status_code == 422
    assert client.post("/sessions", json={"surprise": 1}).status_code == 422

    sid = open_session(client)["id"]
    for bad in (3, -1, "left", "1", True, 1.0, None):
        response = client.post(f"/sessions/{sid}/step", json={"action": bad})
        assert response.status_code == 422, bad
    assert client.post(f"/sessions/{sid}/step", json={}).status_code == 422

    # Forward until the episode ends (a wall is always ahead), then one step too many.
    for _ in range(200):
        if client.post(f"/sessions/{sid}/step", json={"action": 0}).json()["terminated"]:
            break
    over = client.post(f"/sessions/{sid}/step", json={"action": 0})
    assert over.status_code == 409
    assert "reset" in over.json()["detail"]

    too_big = client.post(
        f"/sessions/{sid}/step",
        content=b'{"action": 0, "pad": "' + b"x" * 70_000 + b'"}',
        headers={"content-type": "application/json"},
    )
    assert too_big.status_code == 413
    assert too_big.json() == {
        "detail": "request body too large (this endpoint accepts at most 65536 bytes)",
        "field": "body",
    }


def test_session_limit(client: TestClient) -> None:
    ids = [open_session(client)["id"] for _ in range(3)]
    refused = client.post("/sessions", json={})
    assert refused.status_code == 409
    assert "max_sessions" in refused.json()["detail"]
    client.delete(f"/sessions/{ids[0]}")
    open_session(client)


def test_idle_sessions_make_room_for_new_ones() -> None:
    with make_client(max_sessions=1, session_idle_timeout_s=1.5) as client:
        first = open_session(client)["id"]
        time.sleep(0.9)
        client.get(f"/sessions/{first}")  # a request keeps it alive
        time.sleep(0.9)
        assert client.post("/sessions", json={}).status_code == 409
        time.sleep(1.6)
        second = open_session(client)["id"]
        gone = client.get(f"/sessions/{first}")
        assert gone.status_code == 410 and "without use" in gone.json()["detail"]
        assert [s["id"] for s in client.get("/sessions").json()] == [second]


def test_images(client: TestClient) -> None:
    sid = open_session(client)["id"]
    client.post(f"/sessions/{sid}/step", json={"action": 0})
    png = client.get(f"/sessions/{sid}/map.png")
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    assert png.content.startswith(PNG_MAGIC)
    frame = client.get(f"/sessions/{sid}/frame")
    assert frame.headers["content-type"] == "image/jpeg"
    assert Image.open(io.BytesIO(frame.content)).size == (320, 240)
    top = client.get(f"/sessions/{sid}/frame", params={"view": "topdown", "format": "png"})
    assert top.content.startswith(PNG_MAGIC)
    assert client.get(f"/sessions/{sid}/frame", params={"format": "gif"}).status_code == 422


def test_frames_are_rendered_once_per_state(client: TestClient) -> None:
    sid = open_session(client)["id"]
    session = client.app.state.registry.get(sid)
    first = session.render_frame("camera")
    assert session.render_frame("camera") is first  # idle streams do not re-render
    assert not first.flags.writeable
    client.post(f"/sessions/{sid}/step", json={"action": 1})
    turned = session.render_frame("camera")
    assert turned is not first and not np.array_equal(turned, first)
    assert session.render_frame("topdown").shape != turned.shape


def test_websocket_streams_frames_decoupled_from_stepping(client: TestClient) -> None:
    sid = open_session(client)["id"]
    with client.websocket_connect(f"/sessions/{sid}/stream?fps=30") as ws:
        first = ws.receive_json()
        assert first["type"] == "frame" and first["seq"] == 0
        assert first["frame"]["format"] == "jpeg"
        data = base64.b64decode(first["frame"]["data"])
        assert data.startswith(JPEG_MAGIC) and len(data) == first["frame"]["bytes"]
        assert Image.open(io.BytesIO(data)).size == (320, 240)
        assert first["state"]["step"] == 0
        # Frames keep coming without steps; a step shows up in a later frame's state.
        assert ws.receive_json()["seq"] == 1
        client.post(f"/sessions/{sid}/step", json={"action": 0})
        for _ in range(10):
            message = ws.receive_json()
            if message["state"]["step"] == 1:
                break
        assert message["state"]["step"] == 1
        assert message["state"]["last_marker"]["action"] == 0


def test_websocket_sends_a_frame_right_after_each_action(client: TestClient) -> None:
    sid = open_session(client)["id"]
    with client.websocket_connect(f"/sessions/{sid}/stream?fps=1") as ws:
        assert ws.receive_json()["state"]["step"] == 0
        client.post(f"/sessions/{sid}/step", json={"action": 1})
        stepped = time.monotonic()
        message = ws.receive_json()
        assert message["state"]["step"] == 1
        assert time.monotonic() - stepped < 0.8  # well before the next periodic frame (1 s)


def test_websocket_binary_png_topdown(client: TestClient) -> None:
    sid = open_session(client)["id"]
    url = f"/sessions/{sid}/stream?fps=30&format=png&encoding=binary&view=topdown"
    with client.websocket_connect(url) as ws:
        header = ws.receive_json()
        assert header["frame"]["view"] == "topdown" and "data" not in header["frame"]
        image = ws.receive_bytes()
        assert image.startswith(PNG_MAGIC) and len(image) == header["frame"]["bytes"]


def test_websocket_origin_is_checked_before_accept(client: TestClient) -> None:
    sid = open_session(client)["id"]
    with (
        pytest.raises(WebSocketDisconnect) as refused,
        client.websocket_connect(
            f"/sessions/{sid}/stream", headers={"origin": "http://evil.example"}
        ),
    ):
        pass
    assert refused.value.code == 4403  # before accept: a plain HTTP 403 to real clients
    for origin in ("http://testserver", "http://dashboard.example"):
        with client.websocket_connect(
            f"/sessions/{sid}/stream?fps=30", headers={"origin": origin}
        ) as ws:
            assert ws.receive_json()["type"] == "frame"


def test_websocket_unknown_and_closed_sessions(client: TestClient) -> None:
    with client.websocket_connect("/sessions/nope/stream") as ws:
        assert ws.receive_json()["type"] == "error"
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
        assert closed.value.code == 4404
    sid = open_session(client)["id"]
    with client.websocket_connect(f"/sessions/{sid}/stream?fps=30") as ws:
        assert ws.receive_json()["type"] == "frame"
        client.delete(f"/sessions/{sid}")
        for _ in range(10):
            message = ws.receive_json()
            if message["type"] == "closed":
                break
        assert message["type"] == "closed"
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
        assert closed.value.code == 4410


def test_paced_mode_with_queued_actions(client: TestClient) -> None:
    sid = open_session(client)["id"]
    base = f"/sessions/{sid}/paced"
    assert client.post(f"{base}/actions", json={"actions": [1, 1, 2]}).json() == {
        "queued_actions": 3
    }
    started = client.post(base, json={"policy": "queue", "period_s": 0.05})
    assert started.status_code == 201 and started.json()["running"] is True
    assert client.post(base, json={"policy": "random"}).status_code == 409
    blocked = client.post(f"/sessions/{sid}/step", json={"action": 0})
    assert blocked.status_code == 409 and "paced" in blocked.json()["detail"]
    wait_for(lambda: client.get(base).json()["actions_executed"] == 3)
    state = client.get(f"/sessions/{sid}").json()
    assert state["step"] == 3 and state["last_marker"]["action"] == Action.TURN_RIGHT
    assert client.get(base).json()["running"] is True  # idles while the queue is empty
    client.post(f"{base}/actions", json={"actions": [0]})
    wait_for(lambda: client.get(base).json()["actions_executed"] == 4)
    history = client.get(f"/sessions/{sid}/markers").json()
    assert [m["action"] for m in history] == [1, 1, 2, 0]
    stopped = client.delete(base).json()
    assert stopped["running"] is False and stopped["error"] is None
    assert client.delete(base).status_code == 409
    assert client.post(f"/sessions/{sid}/step", json={"action": 0}).status_code == 200
    too_many = client.post(f"{base}/actions", json={"actions": [0] * 1001})
    assert too_many.status_code == 422


def test_paced_mode_stops_after_max_actions_and_resets_episodes(client: TestClient) -> None:
    sid = open_session(client)["id"]
    base = f"/sessions/{sid}/paced"
    body = {"policy": "oracle", "period_s": 0.05, "max_actions": 25}
    assert client.post(base, json=body).status_code == 201
    wait_for(lambda: not client.get(base).json()["running"])
    paced = client.get(base).json()
    assert paced["actions_executed"] == 25 and paced["error"] is None
    state = client.get(f"/sessions/{sid}").json()
    # The oracle reaches the goal in shortest_path_steps (< 25), then the session resets.
    assert state["episode"] == 1 and state["step"] == 25
    assert client.post(base, json={"period_s": 0.01}).status_code == 422  # below 0.05 s


def test_closing_a_session_stops_its_paced_mode(client: TestClient) -> None:
    sid = open_session(client)["id"]
    client.post(f"/sessions/{sid}/paced", json={"policy": "random", "period_s": 0.05})
    assert client.delete(f"/sessions/{sid}").status_code == 204
    assert client.get(f"/sessions/{sid}/paced").status_code == 410
