"""The dashboard used carelessly or with ill intent: stored markup, odd links, bad or doubled
input, a token revoked mid-use, a viewer, another time zone. Every console error and every
request off 127.0.0.1 fails a test (the ``context`` fixture)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from typing import Any

import pytest

from services.core.db.models import Classifier, HFModel, Job
from services.core.db.session import make_engine, make_session_factory
from services.core.platform import PlatformSettings
from tests.web.conftest import ADMIN, Server, Watch, add_accounts, open_as, serve_api

pytestmark = pytest.mark.slow

MARKUP = '<img src=x onerror="window.pwned=1"></script>\'"&amp;'
"""Stored text that would run or break the page if it were ever parsed as HTML."""


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """The api on a temporary SQLite database with an admin, a staff and a viewer account; no
    worker (these tests watch pages, not jobs run)."""
    from services.api.settings import ApiSettings
    from tests.web.conftest import _skip_reason

    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    root = tmp_path_factory.mktemp("web-outside")
    settings = ApiSettings(
        data_dir=root / "data", admin_email=ADMIN[0], admin_password=ADMIN[1], eeg_url=None
    )
    with serve_api(settings) as base_url:
        srv = Server(base_url, root, {})
        add_accounts(srv)
        yield srv


def seed(server: Server, *rows: Any) -> list[Any]:
    """Rows written to the database as the workers would leave them; their ids."""
    engine = make_engine(PlatformSettings(data_dir=server.root / "data").resolved_database_url)
    try:
        with make_session_factory(engine)() as db:
            db.add_all(rows)
            db.commit()
            return [row.id for row in rows]
    finally:
        engine.dispose()


def posts_to(page: Any, path: str) -> list[str]:
    """Every POST the page sends to ``path`` from now on (a list that grows)."""
    sent: list[str] = []
    page.on(
        "request",
        lambda r: sent.append(r.url) if r.method == "POST" and r.url.endswith(path) else None,
    )
    return sent


def test_stored_markup_is_shown_as_text_everywhere(context: tuple, server: Server) -> None:
    ctx, watch = context
    subject = server.call("POST", "/api/v1/subjects", json={"code": "X-1", "notes": MARKUP})
    rig = server.call("POST", "/api/v1/rigs", json={"name": f"Rig {MARKUP}"})
    start = datetime.now(UTC).replace(microsecond=0) + timedelta(hours=1)
    session = server.call(
        "POST",
        "/api/v1/sessions",
        json={"subject_id": subject["id"], "kind": "online", "rig_id": rig["id"],
              "notes": MARKUP, "scheduled_at": start.isoformat()},
    )  # fmt: skip
    config = {"task": "sssg", "method": "rl_sparse", "seed": 0, "total_steps": 1000}
    job = Job(kind="guided_ppo", config=config, status="failed", attempts=3, error=MARKUP)
    job_id, classifier_id, _ = seed(
        server,
        job,
        Classifier(name=f"clf {MARKUP}", subject_id=subject["id"], metrics={MARKUP: 1.0}),
        HFModel(name=f"hf {MARKUP}", task="sssg", session_id=session["id"]),
    )
    page = open_as(ctx, server, "staff", f"/subjects/{subject['id']}")
    visits = {
        f"/subjects/{subject['id']}": [MARKUP, f"Rig {MARKUP}", f"clf {MARKUP}", f"hf {MARKUP}"],
        "/subjects": [MARKUP],
        f"/sessions?week={start.astimezone().strftime('%G-W%V')}": [f"Rig {MARKUP}"],
        f"/jobs/{job_id}": [MARKUP],
        "/models": [f"clf {MARKUP}", f"hf {MARKUP}"],
        f"/classifiers/{classifier_id}": [f"Calibration: clf {MARKUP}", MARKUP],
        f"/sessions/{session['id']}/live": [f"clf {MARKUP}"],  # the start form's classifier
    }
    for path, texts in visits.items():
        page.goto(path)
        page.wait_for_load_state("networkidle")
        shown = page.locator("main").inner_text() + page.locator("main").evaluate(
            "m => [...m.querySelectorAll('option')].map(o => o.textContent).join('\\n')"
        )
        for text in texts:
            assert text in shown, (path, text)
        assert page.locator("img[src=x]").count() == 0, path
        assert page.evaluate("window.pwned") is None, path
    page.goto("/sessions?week=" + start.astimezone().strftime("%G-W%V"))
    page.locator(f"button[data-session='{session['id']}']").click()
    assert page.locator("dialog[open] p.pre").inner_text() == MARKUP
    assert page.evaluate("window.pwned") is None
    assert watch.console_errors == []


def test_sign_in_never_leads_off_this_site(context: tuple, server: Server) -> None:
    ctx, watch = context
    page = ctx.new_page()
    page.goto("/signin")
    page.locator("input[name=email]").wait_for()
    targets = page.evaluate(
        """async (nexts) => {
            const { nextPath } = await import('/assets/js/pages/signin.js');
            return nexts.map((n) => nextPath('?' + new URLSearchParams({ next: n })));
        }""",
        ["/\\example.invalid/x", "/\t/example.invalid", "//example.invalid", "/\\/example.invalid",
         "https://example.invalid/", "javascript:alert(1)", "/jobs?status=failed#top", ""],
    )  # fmt: skip
    assert targets == [
        "/subjects", "/subjects", "/subjects", "/subjects", "/subjects", "/subjects",
        "/jobs?status=failed#top", "/subjects",
    ]  # fmt: skip
    page.goto("/signin?next=/%5Cexample.invalid/x")  # "/\example.invalid/x": another host
    page.fill("input[name=email]", "staff@lab.test")
    page.fill("input[name=password]", "staff-password-123")
    page.click("button[type=submit]")
    page.wait_for_url(re.compile(r"/subjects$"))
    assert watch.outside == [] and watch.console_errors == []


def test_a_revoked_token_sends_to_sign_in_with_the_reason(context: tuple, server: Server) -> None:
    ctx, watch = context
    email, password = "changes@lab.test", "first-password-123"
    user = server.call(
        "POST", "/api/v1/users", json={"email": email, "password": password, "role": "staff"}
    )
    page = ctx.new_page()
    page.goto("/signin?next=%2Fjobs%3Fstatus%3Dfailed")
    page.fill("input[name=email]", email)
    page.fill("input[name=password]", password)
    page.click("button[type=submit]")
    page.locator("#job-form").wait_for()
    # the admin resets the password (e.g. a shared laptop was lost): earlier tokens end
    server.call("PATCH", f"/api/v1/users/{user['id']}", json={"password": "second-password-123"})
    page.locator("#job-form input[name=total_steps]").fill("1000")
    page.locator("#job-form").get_by_role("button", name="Submit job").click()
    page.wait_for_url(re.compile(r"/signin\?next=%2Fjobs%3Fstatus%3Dfailed$"))
    notice = page.get_by_role("status").filter(has_text="Signed out")
    assert notice.inner_text() == (
        "Signed out: access token issued before the password changed; log in again."
    )
    assert server.call("GET", "/api/v1/jobs", params={"status": "queued"})["total"] == 0
    page.fill("input[name=email]", email)
    page.fill("input[name=password]", "second-password-123")
    page.click("button[type=submit]")
    page.wait_for_url(re.compile(r"/jobs\?status=failed$"))
    page.locator("#jobs-table").wait_for()
    page.goto("/signin")  # said once, not on every visit to the sign-in page
    page.locator("input[name=email]").wait_for()
    assert page.get_by_text("Signed out").count() == 0
    assert watch.errors_except(r"status of 401") == []


def test_a_double_click_sends_one_request(context: tuple, server: Server) -> None:
    ctx, watch = context
    page = open_as(ctx, server, "staff", "/subjects")
    sent = posts_to(page, "/api/v1/subjects")
    page.fill("#new-subject-code", "DBL-1")
    page.get_by_role("button", name="Create subject").dblclick()
    page.get_by_text("Subject DBL-1 created.").wait_for()
    page.wait_for_load_state("networkidle")
    assert len(sent) == 1
    assert page.locator("form[aria-labelledby=new-subject]").get_by_role("alert").count() == 0

    subject = server.call("GET", "/api/v1/subjects", params={"code": "DBL-1"})["items"][0]
    page.goto("/sessions")
    sent = posts_to(page, "/api/v1/sessions")
    form = page.locator("#schedule-form")
    form.locator("select[name=subject_id]").select_option(str(subject["id"]))
    tomorrow = datetime.now() + timedelta(days=1)  # a start to come: no past-date question
    form.locator("input[name=date]").fill(tomorrow.strftime("%Y-%m-%d"))
    form.locator("input[name=time]").fill("10:00")
    form.get_by_role("button", name="Schedule").dblclick()
    page.get_by_text(re.compile(r"^Session \d+ scheduled for")).wait_for()
    assert len(sent) == 1
    sessions = server.call("GET", "/api/v1/sessions", params={"subject_id": subject["id"]})
    assert sessions["total"] == 1
    (session,) = sessions["items"]
    week = datetime.fromisoformat(session["scheduled_at"]).astimezone().strftime("%G-W%V")
    page.goto(f"/sessions?week={week}")
    page.locator(f"button[data-session='{session['id']}']").click()
    cancels = posts_to(page, f"/api/v1/sessions/{session['id']}/cancel")
    page.locator("dialog[open]").get_by_role("button", name="Cancel session").dblclick()
    page.get_by_text(f"Session {session['id']} cancelled.").wait_for()
    assert len(cancels) == 1
    assert watch.console_errors == []


def test_the_apis_refusal_is_shown_at_the_field(context: tuple, server: Server) -> None:
    ctx, watch = context
    subject = server.call("POST", "/api/v1/subjects", json={"code": "FLD-1"})
    page = open_as(ctx, server, "staff", "/sessions")
    form = page.locator("#schedule-form")
    form.locator("select[name=subject_id]").select_option(str(subject["id"]))
    form.locator("input[name=date]").fill("9999-01-01")  # the browser takes it; the API not
    form.get_by_role("button", name="Schedule").click()
    alert = form.get_by_role("alert")
    alert.wait_for()
    assert alert.inner_text().startswith("scheduled_at: must be between 1900-01-01")
    start = form.locator("input[name=time]")
    assert start.get_attribute("aria-invalid") == "true"
    assert (
        form.locator("input[name=time] ~ .field-error")
        .inner_text()
        .startswith("must be between 1900-01-01 and 9000-01-01")
    )
    tomorrow = datetime.now() + timedelta(days=1)  # a start to come: no past-date question
    form.locator("input[name=date]").fill(tomorrow.strftime("%Y-%m-%d"))
    form.get_by_role("button", name="Schedule").click()  # corrected, it is taken
    page.get_by_text(re.compile(r"^Session \d+ scheduled for")).wait_for()
    sessions = server.call("GET", "/api/v1/sessions", params={"subject_id": subject["id"]})
    assert sessions["total"] == 1
    assert watch.errors_except(r"status of 422") == []


def test_unknown_ids_and_weeks_in_the_address(context: tuple, server: Server) -> None:
    ctx, watch = context
    page = open_as(ctx, server, "viewer", "/subjects")
    missing = {
        "/subjects/99999": ("no subject with id 99999", "Subjects"),
        "/subjects/0": ("No subject has the id 0.", "Subjects"),
        "/classifiers/99999999999": ("No classifier has the id 99999999999.", "Models"),
        "/jobs/not-a-job": ("no job with id not-a-job", "Jobs"),
        "/sessions/99999/live": ("no session with id 99999", "Sessions"),
    }
    for path, (text, back) in missing.items():
        page.goto(path)
        page.get_by_role("heading", name="Not found").wait_for()
        assert page.get_by_role("alert").inner_text() == text
        assert page.title() == "Not found · Brain-guided RL platform"
        page.get_by_role("link", name=f"Back to {back}").wait_for()
    page.get_by_role("link", name="Back to Sessions").click()
    page.locator("table.week").wait_for()

    for week in ("2026-W99", "2026-W00", "2025-W53"):  # 2025 has 52 ISO weeks
        page.goto(f"/sessions?week={week}")
        page.locator("table.week").wait_for()
        this_week = page.locator("table.week caption").inner_text().split()[1]
        assert page.get_by_role("status").inner_text() == (
            f"There is no week {week}: this is week {this_week}."
        )
    page.goto("/sessions?week=2026-W53")  # 2026 has 53
    assert page.locator("table.week caption").inner_text().startswith("Week 2026-W53 ")
    assert watch.errors_except(r"status of 404 \(Not Found\)") == []


def test_a_failed_job_for_staff_and_viewer(context: tuple, server: Server) -> None:
    """A job that failed before its first evaluation: its page asks for no figure that cannot
    exist (no 404 in the console); staff may retry it, a viewer is offered nothing; the list's
    filters cover every kind and stay in the address."""
    ctx, watch = context
    config = {"task": "vssg", "method": "rl_rich", "seed": 4, "total_steps": 1000}
    (job_id,) = seed(
        server, Job(kind="guided_ppo", config=config, status="failed", attempts=3, error="OOM")
    )
    (export_id,) = seed(server, Job(kind="bids_export", config={"subject_id": 1}, status="failed"))
    page = open_as(ctx, server, "viewer", f"/jobs/{job_id}")
    page.get_by_role("heading", name=f"Job {job_id[:8]} failed").wait_for()
    page.wait_for_load_state("networkidle")
    assert page.get_by_text("The learning curve's PNG comes with its first evaluation.").count()
    assert page.get_by_role("button", name=re.compile("Retry|Cancel")).count() == 0

    page.goto("/jobs")
    page.locator(f"tr[data-job='{job_id}']").wait_for()
    kinds = page.locator("#filter-kind option").evaluate_all("os => os.map((o) => o.value)")
    assert kinds == ["", "guided_ppo", "reproduce", "reproduce_run", "reproduce_batch",
                     "eeg_calibration", "live_session", "bids_export",
                     "session_replay"]  # fmt: skip
    page.locator("#filter-kind").select_option("bids_export")
    page.locator(f"tr[data-job='{export_id}']").wait_for()
    page.locator("#filter-status").select_option("failed")
    assert page.url.endswith("/jobs?status=failed&kind=bids_export")
    page.reload()
    page.locator(f"tr[data-job='{export_id}']").wait_for()
    assert page.locator("#jobs-table tbody tr").count() == 1
    assert page.get_by_role("button", name="Retry").count() == 0  # a viewer
    page.goto(f"/jobs/{export_id}")
    page.get_by_text("bids_export jobs have no learning curve.").wait_for()
    page.wait_for_load_state("networkidle")

    staff = open_as(ctx, server, "staff", f"/jobs/{job_id}")
    retries = posts_to(staff, f"/api/v1/jobs/{job_id}/retry")
    staff.get_by_role("button", name="Retry").dblclick()
    staff.get_by_text(f"Job {job_id[:8]} queued again.").wait_for()
    staff.wait_for_load_state("networkidle")
    assert len(retries) == 1
    server.call("POST", f"/api/v1/jobs/{job_id}/cancel")
    assert watch.console_errors == []


def test_times_are_the_browsers_local_times(browser: Any, server: Server) -> None:
    """A browser in Los Angeles (UTC-8 in December) schedules late on a Sunday: the API
    stores Monday in UTC and the week shows it on the Sunday it was given."""
    ctx = browser.new_context(
        base_url=server.base_url, viewport={"width": 1280, "height": 800},
        timezone_id="America/Los_Angeles",
    )  # fmt: skip
    watch = Watch(server.base_url)
    ctx.route("**/*", watch.route)
    ctx.on("weberror", lambda error: watch.console_errors.append(str(error.error)))
    errors = watch.console_errors
    ctx.on("console", lambda msg: errors.append(msg.text) if msg.type == "error" else None)
    try:
        subject = server.call("POST", "/api/v1/subjects", json={"code": "TZ-1"})
        page = open_as(ctx, server, "staff", "/sessions?week=2027-W02")
        assert page.locator("table.week caption").inner_text() == (
            "Week 2027-W02 (America/Los_Angeles)"
        )
        form = page.locator("#schedule-form")
        form.locator("select[name=subject_id]").select_option(str(subject["id"]))
        form.locator("input[name=date]").fill("2027-01-17")  # the Sunday of 2027-W02
        form.locator("input[name=time]").fill("23:30")
        form.locator("input[name=duration_minutes]").fill("20")
        form.get_by_role("button", name="Schedule").click()
        page.get_by_text(re.compile(r"^Session \d+ scheduled for Jan 17, 2027, 11:30")).wait_for()
        assert page.url.endswith("/sessions?week=2027-W02")
        sessions = server.call("GET", "/api/v1/sessions", params={"subject_id": subject["id"]})
        (session,) = sessions["items"]
        assert session["scheduled_at"] == "2027-01-18T07:30:00Z"
        sunday = page.locator("table.week tbody tr", has_text="No rig").locator("td").nth(6)
        assert (
            sunday.locator(f"button[data-session='{session['id']}']")
            .inner_text()
            .startswith("11:30 PM–11:50 PM TZ-1")
        )
        assert watch.console_errors == [] and watch.outside == []
    finally:
        ctx.close()
