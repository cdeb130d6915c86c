"""The live pages in Debian's Chromium against a real sim service: the operator's live view
and the subject display receive the robot's frames through the api's relay (token and
service token checked for real), show each action's decoded feedback beside the oracle
label as rows arrive, reconnect after a dropped frame connection without losing the table,
and the display reports the frames it showed.

The sim session is stepped by this test, which writes the rows the live-session runner
writes (one marker per executed action with the sim's own marker, then the decision): the
decoded feedback here is seeded by the test (p_error 0.2 for an action the oracle judges
correct, 0.8 for an error, every fourth one wrong), not decoded from EEG, so the page's
accuracy has a known value. The full chain (runner, EEG, learner) is tested in tests/loop.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path

import httpx
import pytest

from services.core.db.base import utcnow
from services.core.db.live import LiveDecision, LiveMarker, LiveRun
from services.core.db.session import make_engine, make_session_factory
from services.sim.maps import DEFAULT_MAP_PATH, load_map
from services.sim.oracle import Oracle
from services.sim.settings import SimSettings
from tests.web.conftest import (
    ADMIN,
    STAFF,
    Server,
    _free_port,
    _login,
    _skip_reason,
    _stop,
    open_as,
)

TOKEN = "web-live-service-token-0123"
STEPS = 8


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """The api (relaying to a real sim process with the service token) and the sim."""
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    import uvicorn
    from argon2 import PasswordHasher

    from services.api import security
    from services.api.app import create_app
    from services.api.settings import ApiSettings

    root = tmp_path_factory.mktemp("web-live")
    data_dir = root / "data"
    Oracle.for_map(load_map(DEFAULT_MAP_PATH), SimSettings(data_dir=data_dir).oracle_cache_dir)
    sim_port = _free_port()
    env = {
        **{k: v for k, v in os.environ.items() if not k.startswith("BGRL_")},
        "BGRL_DATA_DIR": str(data_dir),
        "BGRL_SERVICE_TOKEN": TOKEN,
        "BGRL_LOG_LEVEL": "WARNING",
    }
    sim = subprocess.Popen(
        [sys.executable, "-m", "uvicorn", "services.sim.app:app", "--host", "127.0.0.1",
         "--port", str(sim_port)],
        env=env, cwd=root, stdout=(root / "sim.log").open("wb"), stderr=subprocess.STDOUT,
    )  # fmt: skip
    settings = ApiSettings(
        data_dir=data_dir,
        admin_email=ADMIN[0],
        admin_password=ADMIN[1],
        eeg_url=None,
        sim_url=f"http://127.0.0.1:{sim_port}",
        service_token=TOKEN,
    )
    patch = pytest.MonkeyPatch()
    patch.setattr(security, "_hasher", PasswordHasher(time_cost=1, memory_cost=64, parallelism=1))
    port = _free_port()
    config = uvicorn.Config(create_app(settings), host="127.0.0.1", port=port, log_level="warning")
    api = uvicorn.Server(config)
    thread = threading.Thread(target=api.run, name="api", daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 90
        while True:
            try:
                sim_up = httpx.get(f"http://127.0.0.1:{sim_port}/health", timeout=2).is_success
            except httpx.HTTPError:
                sim_up = False
            if sim_up and api.started:
                break
            assert time.monotonic() < deadline, (root / "sim.log").read_text()
            time.sleep(0.2)
        srv = Server(f"http://127.0.0.1:{port}", root, env)
        srv.sim_url = f"http://127.0.0.1:{sim_port}"  # type: ignore[attr-defined]
        srv.database_url = settings.resolved_database_url  # type: ignore[attr-defined]
        srv.tokens["admin"] = _login(srv.base_url, *ADMIN)
        srv.call("POST", "/api/v1/users", json={"email": STAFF[0], "password": STAFF[1],
                                                 "role": "staff"})  # fmt: skip
        srv.tokens["staff"] = _login(srv.base_url, *STAFF)
        yield srv
    finally:
        api.should_exit = True
        thread.join(timeout=15)
        _stop(sim)
        patch.undo()


class SteppedSession:
    """A lab session whose live run is a real sim session stepped by the test."""

    def __init__(self, server: Server) -> None:
        subject = server.call("POST", "/api/v1/subjects", json={"code": "LIVE-1"})
        start = utcnow() + timedelta(minutes=1)
        self.lab = server.call(
            "POST",
            "/api/v1/sessions",
            json={"subject_id": subject["id"], "kind": "online",
                  "scheduled_at": start.isoformat(), "duration_minutes": 30},
        )  # fmt: skip
        # the first session builds the map's oracle: seconds, more on a loaded machine
        self.sim = httpx.Client(
            base_url=server.sim_url,  # type: ignore[attr-defined]
            headers={"X-Service-Token": TOKEN},
            timeout=120.0,
        )
        created = self.sim.post("/sessions", json={"task": "sssg", "seed": 5}).json()
        self.sim_id = created["id"]
        self.observation = created["observation"]
        self.sessions = make_session_factory(make_engine(server.database_url))  # type: ignore[attr-defined]
        with self.sessions() as db:
            run = LiveRun(session_id=self.lab["id"], mode="online", status="running",
                          sim_session_id=self.sim_id,
                          options={"accelerated": True, "label_budget": 100})  # fmt: skip
            db.add(run)
            db.commit()
            self.run_id = run.id
        self.expected: list[tuple[int, str, str]] = []

    def step(self, step: int) -> None:
        """Execute one action in the sim; write its marker row, then its decision row."""
        action = step % 3
        out = self.sim.post(f"/sessions/{self.sim_id}/step", json={"action": action}).json()
        marker = out["marker"]
        correct = bool(marker["correct"])
        wrong = step % 4 == 3
        decoded = "correct" if correct != wrong else "error"
        with self.sessions() as db:
            db.add(LiveMarker(run_id=self.run_id, session_id=self.lab["id"], step=step,
                              sim_session_id=self.sim_id, sim_step=marker["step"],
                              episode=marker["episode"], action=action, oracle_correct=correct,
                              observation=self.observation, marker_ts=marker["timestamp"],
                              eeg_ts=marker["timestamp"], executed_at=utcnow()))  # fmt: skip
            db.commit()
            time.sleep(0.15)
            db.add(LiveDecision(run_id=self.run_id, session_id=self.lab["id"], step=step,
                                status="ok", feedback=decoded,
                                p_error=0.8 if decoded == "error" else 0.2,
                                oracle_correct=correct, epoch_end_ts=10.0 + step,
                                decided_ts=10.0 + step + 0.012))  # fmt: skip
            db.commit()
        self.observation = out["observation"]
        if out["terminated"] or out["truncated"]:
            self.observation = self.sim.post(f"/sessions/{self.sim_id}/reset").json()["observation"]
        self.expected.append((step, "correct" if correct else "error", decoded))


def _wait_decoded(page, step: int) -> None:
    """Until the row of ``step`` shows its decoded feedback."""
    page.wait_for_function(
        "(sel) => ['correct', 'error'].includes(document.querySelector(sel)?.textContent)",
        arg=f"#live-actions tr[data-step='{step}'] td.decoded",
    )


def test_live_view_and_display_show_frames_feedback_and_reconnect(
    context: tuple, server: Server, screenshot_dir: Path
) -> None:
    ctx, watch = context
    session = SteppedSession(server)
    sid = session.lab["id"]
    live = open_as(ctx, server, "staff", f"/sessions/{sid}/live")
    display = ctx.new_page()
    display.goto(f"/sessions/{sid}/display")
    # Frames arrive through the relay before any action (the sim streams at 2 fps).
    live.wait_for_function("() => document.getElementById('live-frame').naturalWidth > 0")
    display.wait_for_function("() => document.getElementById('display-frame').naturalWidth > 0")
    assert display.locator("nav").is_hidden() and display.locator("button:visible").count() == 0

    for step in range(STEPS // 2):
        session.step(step)
    _wait_decoded(live, STEPS // 2 - 1)
    # Drop the frame connection: the view reconnects and keeps its rows.
    live.evaluate("window.bgrlLiveView.frames.drop()")
    live.wait_for_function(
        "() => document.getElementById('live-connection').textContent === 'connected'"
    )
    for step in range(STEPS // 2, STEPS):
        session.step(step)
    last = STEPS - 1
    _wait_decoded(live, last)
    live.wait_for_function(
        "() => document.getElementById('current-action').textContent.startsWith('Now: ')"
    )
    rows = live.locator("#live-actions tr")
    assert rows.count() == STEPS
    for step, oracle, decoded in session.expected:
        cells = live.locator(f"#live-actions tr[data-step='{step}'] td").all_inner_texts()
        assert cells[0] == str(step) and cells[2] == oracle and cells[3] == decoded
        assert cells[4] == ("0.800" if decoded == "error" else "0.200") and cells[5] == "12.0 ms"
    hits = sum(1 for _, oracle, decoded in session.expected if oracle == decoded)
    live.wait_for_function(
        "(text) => document.getElementById('live-stats').textContent.includes(text)",
        arg=f"{round(100 * hits / STEPS, 1):.1f} %",
    )
    # The display reported when it showed the frame of each action it saw.
    deadline = time.monotonic() + 10
    while True:
        shown = server.call("GET", f"/api/v1/sessions/{sid}/events", params={"kind": "frames"})
        if shown["total"] >= 1 or time.monotonic() > deadline:
            break
        time.sleep(0.3)
    assert shown["total"] >= 1
    assert {item["step"] for item in shown["items"]} <= set(range(STEPS))
    live.screenshot(path=str(screenshot_dir / "live.png"), full_page=True)
    display.screenshot(path=str(screenshot_dir / "display.png"))
    assert watch.errors_except() == []


def test_subject_page_links_the_live_view_and_starts_a_bids_export(
    context: tuple, server: Server
) -> None:
    ctx, watch = context
    subjects = server.call("GET", "/api/v1/subjects", params={"code": "LIVE-1"})["items"]
    assert subjects, "runs after the live test, which creates subject LIVE-1"
    subject = subjects[0]
    page = open_as(ctx, server, "staff", f"/subjects/{subject['id']}")
    page.get_by_role("button", name="Export as BIDS").click()
    link = page.get_by_role("link", name=re.compile(r"^job [0-9a-f]{8}$"))
    link.wait_for()
    job_id = link.get_attribute("href").rsplit("/", 1)[-1]
    job = server.call("GET", f"/api/v1/jobs/{job_id}")
    assert job["kind"] == "bids_export" and job["config"] == {"subject_id": subject["id"]}
    assert page.get_by_role("link", name="Live view").count() == 0  # the session is scheduled
    assert watch.errors_except() == []
