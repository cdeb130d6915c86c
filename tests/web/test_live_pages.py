"""The live pages in Debian's Chromium against the real services: the operator's live view
and the subject display receive the robot's frames through the api's relay (token and
service token checked for real), show each action's decoded feedback beside the oracle
label as rows arrive, reconnect after a dropped frame connection without losing the table,
and the display reports the frames it showed.

Two ways in. ``test_live_view_and_display_...`` steps a sim session itself and writes the
rows the live-session runner writes, with the decoded feedback seeded (p_error 0.2 for an
action the oracle judges correct, 0.8 for an error, every fourth one wrong), so every cell
and the accuracy have known values. ``test_accelerated_online_session_...`` is the whole
chain: staff start an accelerated online session of the virtual subject from the dashboard,
and a real ``bgrl worker`` runs it through the sim, EEG and learner services with a
classifier from a real (small) calibration session.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable, Iterator
from datetime import timedelta
from pathlib import Path
from typing import Any

import httpx
import pytest

from services.core.db.base import utcnow
from services.core.db.live import LiveDecision, LiveMarker, LiveRun
from services.core.db.models import LabSession
from services.core.db.session import make_engine, make_session_factory
from services.sim.maps import DEFAULT_MAP_PATH, load_map
from services.sim.oracle import Oracle
from services.sim.settings import SimSettings
from tests.helpers import env_without_bgrl, stop_processes
from tests.web.conftest import (
    ADMIN,
    Server,
    _skip_reason,
    add_accounts,
    open_as,
    run_services,
    serve_api,
)

TOKEN = "web-live-service-token-0123"
STEPS = 8


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """The api (relaying frames from the sim with the service token), the sim, EEG and
    learner services and a real ``bgrl worker`` running live sessions through them, all on
    loopback sharing one data folder and service token."""
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    from services.api.settings import ApiSettings

    root = tmp_path_factory.mktemp("web-live")
    data_dir = root / "data"
    # built once here: the sim and the worker's runner would each build it on first use
    Oracle.for_map(load_map(DEFAULT_MAP_PATH), SimSettings(data_dir=data_dir).oracle_cache_dir)
    env = {
        **env_without_bgrl(),
        "BGRL_DATA_DIR": str(data_dir),
        "BGRL_SERVICE_TOKEN": TOKEN,
        "BGRL_LOG_LEVEL": "WARNING",
    }
    with run_services(root, env, ("sim", "eeg", "learner")) as urls:
        settings = ApiSettings(
            data_dir=data_dir,
            admin_email=ADMIN[0],
            admin_password=ADMIN[1],
            eeg_url=None,
            sim_url=urls["sim"],
            service_token=TOKEN,
            job_heartbeat_s=0.5,
        )
        with serve_api(settings) as base_url:
            worker_env = {
                **env,
                **{f"BGRL_{name.upper()}_URL": url for name, url in urls.items()},
                "BGRL_JOB_HEARTBEAT_S": "0.5",
                "BGRL_LOG_LEVEL": "INFO",
            }
            srv = Server(base_url, root, worker_env, sim_url=urls["sim"],
                         database_url=settings.resolved_database_url)  # fmt: skip
            srv.start_worker()
            try:
                add_accounts(srv, ("staff",))
                yield srv
            finally:
                if srv.worker is not None:
                    # killed 2 s after SIGTERM: a warm shutdown would first finish the last
                    # test's BIDS export (cancelled, but only seen after the export, 10+ s)
                    stop_processes([srv.worker], timeout_s=2)


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
            base_url=server.sim_url,
            headers={"X-Service-Token": TOKEN},
            timeout=120.0,
        )
        created = self.sim.post("/sessions", json={"task": "sssg", "seed": 5}).json()
        self.sim_id = created["id"]
        self.observation = created["observation"]
        self.sessions = make_session_factory(make_engine(server.database_url))
        with self.sessions() as db:  # what POST /sessions/{id}/start and the runner write
            run = LiveRun(session_id=self.lab["id"], mode="online", status="running",
                          sim_session_id=self.sim_id,
                          options={"accelerated": True, "label_budget": 100})  # fmt: skip
            db.add(run)
            lab = db.get(LabSession, self.lab["id"])
            assert lab is not None
            lab.status = "running"
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
    ctx.set_default_timeout(30_000)  # the worker calibrates meanwhile (fixture calibration)
    session = SteppedSession(server)
    sid = session.lab["id"]
    live = open_as(ctx, server, "staff", f"/sessions/{sid}/live")
    display = ctx.new_page()
    display.goto(f"/sessions/{sid}/display")
    # Frames arrive through the relay before any action (the sim streams at 2 fps).
    live.wait_for_function("() => document.getElementById('live-frame')?.naturalWidth > 0")
    display.wait_for_function("() => document.getElementById('display-frame')?.naturalWidth > 0")
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
    display.screenshot(path=str(screenshot_dir / "display.png"))
    assert watch.errors_except() == []


# A real classifier, made the platform's way but small: an accelerated calibration session of
# the virtual subject with 60 actions (the paper records ~600) at full ErrP strength, and its
# eeg_calibration job with at most 30 training passes (300 by default): ~30 s, not minutes.
# How well it decodes is not what this test checks; that the page shows what it decodes is.
CALIBRATION = {"accelerated": True, "n_actions": 60, "virtual_quality": 1.0, "seed": 1,
               "calibration_max_passes": 30}  # fmt: skip
ROWS_BEFORE_STOP = 4
"""Decoded actions the page must show before the test stops the session."""


def _schedule(server: Server, subject_id: int, kind: str, in_minutes: int) -> dict[str, Any]:
    start = utcnow() + timedelta(minutes=in_minutes)
    return server.call(
        "POST",
        "/api/v1/sessions",
        json={"subject_id": subject_id, "kind": kind, "scheduled_at": start.isoformat(),
              "duration_minutes": 20},
    )  # fmt: skip


def _poll(read: Callable[[], Any], done: Callable[[Any], bool], timeout: float, what: str) -> Any:
    """``read()`` until ``done`` of it; fail naming ``what`` and the last answer."""
    deadline = time.monotonic() + timeout
    while True:
        value = read()
        if done(value):
            return value
        assert time.monotonic() < deadline, f"{what} within {timeout} s: {value}"
        time.sleep(0.5)


@pytest.fixture(scope="module", autouse=True)
def calibration(server: Server) -> tuple[int, int]:
    """Start the calibration session as soon as the platform is up, so that the worker runs
    it while the first test drives the browser; (subject id, its lab session id)."""
    subject = server.call("POST", "/api/v1/subjects", json={"code": "LIVE-2"})
    cal = _schedule(server, subject["id"], "calibration", in_minutes=1)
    server.call("POST", f"/api/v1/sessions/{cal['id']}/start", role="staff", json=CALIBRATION)
    return subject["id"], cal["id"]


@pytest.fixture(scope="module")
def calibrated(server: Server, calibration: tuple[int, int]) -> tuple[int, int]:
    """The subject and the classifier its calibration session and eeg_calibration job made."""
    subject_id, session_id = calibration
    live = _poll(
        lambda: server.call("GET", f"/api/v1/sessions/{session_id}/live"),
        lambda live: live["run"]["status"] not in ("queued", "running"),
        240,
        "the calibration session ends",
    )
    assert live["run"]["status"] == "completed", live
    job = _poll(
        lambda: server.call("GET", f"/api/v1/jobs/{live['run']['follow_up_job_id']}"),
        lambda job: job["status"] in ("succeeded", "failed", "cancelled"),
        240,
        "its eeg_calibration job ends",
    )
    assert job["status"] == "succeeded", job
    made = server.call("GET", "/api/v1/classifiers", params={"subject_id": subject_id})
    (classifier,) = [c for c in made["items"] if c["job_id"] == job["id"]]
    return subject_id, classifier["id"]


def _stat(page: Any, name: str) -> str:
    """The value of one figure of the live view (``<dt>name</dt><dd>value</dd>``)."""
    xpath = f"//dl[@id='live-stats']/dt[.='{name}']/following-sibling::dd[1]"
    return page.locator(f"xpath={xpath}").inner_text()


def _wait_stat(page: Any, name: str, pattern: str, timeout_s: float = 15.0) -> None:
    """Until the figure ``name`` of the live view matches ``pattern`` (a JS regex)."""
    page.wait_for_function(
        """([name, pattern]) => new RegExp(pattern).test([...document.querySelectorAll(
              '#live-stats dt')].find((dt) => dt.textContent === name)?.nextElementSibling
              .textContent)""",
        arg=[name, pattern],
        timeout=timeout_s * 1000,
    )


def test_accelerated_online_session_of_the_virtual_subject_in_the_live_view(
    context: tuple, server: Server, calibrated: tuple[int, int], screenshot_dir: Path
) -> None:
    ctx, watch = context
    subject_id, classifier_id = calibrated
    online = _schedule(server, subject_id, "online", in_minutes=30)
    sid = online["id"]
    # Staff reach the scheduled session's live view from the subject's page and start it
    # there: accelerated, the virtual subject, the subject's classifier.
    page = open_as(ctx, server, "staff", f"/subjects/{subject_id}")
    page.locator(f"a[href='/sessions/{sid}/live']").click()
    page.wait_for_url(f"**/sessions/{sid}/live")
    assert _stat(page, "Status") == "not started"
    form = page.get_by_role("form", name="Start the session")
    form.get_by_label("Classifier").select_option(str(classifier_id))
    assert form.get_by_label("Label budget").input_value() == "1000"  # not reached: stopped
    assert form.get_by_label("Stage-2 method").input_value() == ""  # the recommended one
    form.get_by_label("Stage-2 method").select_option("categorical")
    assert form.get_by_label("Label channel").input_value() == ""  # soft if calibrated
    form.get_by_label("Label channel").select_option("soft")
    assert form.get_by_label("Accelerated (virtual subject)").is_checked()
    form.get_by_role("button", name="Start").click()
    page.get_by_text("Session started.").wait_for()
    form.wait_for(state="hidden")

    # Frames arrive through the relay while the worker runs the session, and they move.
    page.wait_for_function("() => document.getElementById('live-frame')?.naturalWidth > 0")
    page.wait_for_function(
        "() => document.getElementById('current-action').textContent.startsWith('Now: ')"
    )
    first = page.locator("#current-action").inner_text()
    page.wait_for_function(
        "(first) => document.getElementById('current-action').textContent !== first", arg=first
    )
    # Per action: the decoded feedback and its probability beside the oracle label; then the
    # running accuracy and the labels against the budget.
    page.wait_for_function(
        """(n) => [...document.querySelectorAll('#live-actions td.decoded')]
              .filter((td) => ['correct', 'error'].includes(td.textContent)).length >= n""",
        arg=ROWS_BEFORE_STOP,
        timeout=120_000,
    )
    _wait_stat(page, "Running accuracy", r"^\d+\.\d %$")
    _wait_stat(page, "Labels", r"^[1-9]\d* / 1000$")
    assert _stat(page, "Status") == "running"
    page.screenshot(path=str(screenshot_dir / "live.png"), full_page=True)

    page.get_by_role("button", name="Stop").click()
    page.get_by_text("Stop requested").wait_for()
    page.wait_for_function(
        "() => document.querySelector('#live-stats .badge')?.textContent === 'stopped'",
        timeout=120_000,
    )
    live = server.call("GET", f"/api/v1/sessions/{sid}/live")
    run = live["run"]
    assert run["result"]["stopped_on_command"] is True and run["hf_model_id"] is not None
    assert run["options"]["classifier_id"] == classifier_id and run["options"]["accelerated"]
    assert run["options"]["hf_method"] == run["hf_method"] == "categorical"
    assert run["options"]["label_channel"] == run["label_channel"] == "soft"
    # The page's table is the run's rows: every action, its oracle label, decoded feedback
    # and p(error) as the worker stored them; its running accuracy is the API's.
    rows = page.locator("#live-actions tr")
    page.wait_for_function(
        "(n) => document.querySelectorAll('#live-actions tr').length === n", arg=live["markers"]
    )
    decisions = server.call(
        "GET", f"/api/v1/sessions/{sid}/events", params={"kind": "decisions", "limit": 500}
    )["items"]
    assert live["decisions_accepted"] >= ROWS_BEFORE_STOP and len(decisions) == rows.count()
    page.wait_for_function(
        "() => [...document.querySelectorAll('#live-actions td.decoded')]"
        ".every((td) => td.textContent !== 'pending')"
    )
    for decision in decisions:
        cells = page.locator(f"#live-actions tr[data-step='{decision['step']}'] td")
        step, _, oracle, decoded, p_error, _ = cells.all_inner_texts()
        assert step == str(decision["step"])
        assert oracle == ("correct" if decision["oracle_correct"] else "error")
        if decision["status"] == "ok":
            assert (decoded, p_error) == (decision["feedback"], f"{decision['p_error']:.3f}")
        else:
            assert decoded == "rejected"
    assert _stat(page, "Running accuracy") == f"{100 * live['running_accuracy']:.1f} %"
    assert watch.errors_except() == []


def test_a_failed_run_resumes_from_the_live_view(
    context: tuple, server: Server, calibrated: tuple[int, int]
) -> None:
    """A test session whose run failed (as the runner leaves it when a service stayed down
    past its retry window) is resumed from the live view with the options it began with,
    and the worker finishes it."""
    ctx, watch = context
    subject_id, classifier_id = calibrated
    lab = _schedule(server, subject_id, "test", in_minutes=60)
    options = {"accelerated": True, "n_actions": 3, "classifier_id": classifier_id,
               "virtual_quality": 1.0}  # fmt: skip
    sessions = make_session_factory(make_engine(server.database_url))
    with sessions() as db:
        db.add(LiveRun(session_id=lab["id"], mode="test", options=options, status="failed",
                       error="sim stayed unreachable for 60 s"))  # fmt: skip
        row = db.get(LabSession, lab["id"])
        assert row is not None
        row.status = "running"
        db.commit()
    page = open_as(ctx, server, "staff", f"/sessions/{lab['id']}/live")
    _wait_stat(page, "Status", "^failed$")
    assert _stat(page, "Error") == "sim stayed unreachable for 60 s"
    assert page.get_by_role("button", name="Stop").is_hidden()
    page.get_by_role("button", name="Resume").click()
    page.get_by_text("Session resumed").wait_for()
    _wait_stat(page, "Status", "^completed$", timeout_s=120)
    page.wait_for_function(
        """() => [...document.querySelectorAll('#live-actions td.decoded')]
              .filter((td) => ['correct', 'error', 'rejected'].includes(td.textContent))
              .length === 3"""
    )
    assert page.get_by_role("button", name="Resume").is_hidden()
    run = server.call("GET", f"/api/v1/sessions/{lab['id']}/live")["run"]
    assert run["options"] == options and run["result"]["decisions"] == 3
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
    server.call("POST", f"/api/v1/jobs/{job_id}/cancel")  # the module's worker has done its part
    live = page.get_by_role("link", name="Live view")  # LIVE-1's session has started
    assert live.count() == 1 and live.get_attribute("href").endswith("/live")
    assert watch.errors_except() == []
