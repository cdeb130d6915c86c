"""What lab staff do from the dashboard beyond jobs and sessions, as each role: accounts,
rigs with their channel maps, API tokens and passwords, the audit log (admin pages);
recordings (upload with progress and the refusal at the field, calibrate, delete with the
job-in-use guard); a finished calibration session's links; ids people can type; the
schedule form's careless input. A real EEG service (in a thread) validates the uploads; no
worker. Every console error and request off 127.0.0.1 fails a test."""

from __future__ import annotations

import re
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import httpx
import pytest

from services.core.db.base import utcnow
from services.core.db.live import LiveMarker, LiveRun
from services.core.db.models import Classifier, Job
from tests.helpers import serve_in_thread
from tests.web.conftest import ADMIN, Server, add_accounts, open_as, serve_api
from tests.web.test_dashboard_outside_use import seed

pytestmark = pytest.mark.slow
expect = pytest.importorskip("playwright.sync_api", reason="playwright is not installed").expect


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """The api on a temporary SQLite database with an admin, a staff and a viewer account,
    and the real EEG service (in a thread) validating uploads."""
    from services.api.settings import ApiSettings
    from services.eeg.service.app import create_app as create_eeg_app
    from services.eeg.service.settings import EEGSettings
    from tests.web.conftest import _skip_reason

    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    root = tmp_path_factory.mktemp("web-staff")
    eeg = EEGSettings(data_dir=root / "eeg", max_upload_bytes=8 * 2**20)
    with serve_in_thread(create_eeg_app(eeg)) as eeg_url:
        settings = ApiSettings(
            data_dir=root / "data", admin_email=ADMIN[0], admin_password=ADMIN[1], eeg_url=eeg_url
        )
        with serve_api(settings) as base_url:
            srv = Server(base_url, root, {})
            add_accounts(srv)
            yield srv


@pytest.fixture(scope="module")
def synthetic_bdf(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small synthetic recording (virtual subject, 256 Hz, 12 actions) as a BDF file."""
    from services.eeg.recordings.io import write_bdf
    from services.eeg.virtual.subject import SyntheticRecording

    path = tmp_path_factory.mktemp("bdf") / "s01.bdf"
    write_bdf(SyntheticRecording([True, False] * 6, quality=0.8, seed=1, sfreq=256.0), path)
    return path


def _signs_in(server: Server, email: str, password: str) -> bool:
    answer = httpx.post(
        server.base_url + "/api/v1/auth/token", data={"username": email, "password": password}
    )
    return answer.status_code == 200


def test_admin_pages_are_for_admins_only(context: tuple, server: Server) -> None:
    ctx, watch = context
    for role in ("staff", "viewer"):
        page = open_as(ctx, server, role, "/subjects")
        assert page.get_by_role("link", name="Users").count() == 0
        assert page.get_by_role("link", name="Recordings").is_visible()
        page.goto("/admin/users")
        page.get_by_role("heading", name="Admins only").wait_for()
        page.close()
    page = open_as(ctx, server, "admin", "/subjects")
    for name in ("Users", "Rigs", "Audit"):
        assert page.get_by_role("link", name=name, exact=True).is_visible()
    assert watch.errors_except() == []


def test_admin_creates_deactivates_and_resets_accounts(
    context: tuple, server: Server, screenshot_dir: Path
) -> None:
    ctx, watch = context
    page = open_as(ctx, server, "admin", "/admin/users")
    form = page.locator("#user-form")
    form.locator("input[name=email]").fill("jane")
    form.get_by_role("button", name="Create account").click()
    error = form.locator("input[name=email] ~ .field-error")
    error.filter(has_text="'jane' is not an e-mail address like name@lab.org").wait_for()

    form.locator("input[name=email]").fill("new.staff@lab.test")
    form.locator("select[name=role]").select_option("staff")
    form.get_by_role("button", name="Create account").click()
    secret = page.locator("#one-time-password input.secret")
    secret.wait_for()
    password = secret.input_value()
    assert len(password) == 16 and _signs_in(server, "new.staff@lab.test", password)
    page.screenshot(path=str(screenshot_dir / "admin-users.png"), full_page=True)

    form.locator("input[name=email]").fill("new.staff@lab.test")  # again: refused
    form.get_by_role("button", name="Create account").click()
    form.get_by_role("alert").filter(has_text="new.staff@lab.test").wait_for()

    row = page.locator("tr", has_text="new.staff@lab.test")
    row.get_by_role("button", name="Deactivate").click()
    page.get_by_text("new.staff@lab.test deactivated: they can no longer sign in.").wait_for()
    assert not _signs_in(server, "new.staff@lab.test", password)
    row.get_by_role("button", name="Reactivate").click()
    page.get_by_text("new.staff@lab.test can sign in again.").wait_for()
    row.get_by_role("button", name="Reset password").click()
    page.get_by_text("Password of new.staff@lab.test reset").wait_for()
    new_password = page.locator("#one-time-password input.secret").input_value()
    assert new_password != password
    assert _signs_in(server, "new.staff@lab.test", new_password)
    assert not _signs_in(server, "new.staff@lab.test", password)
    row.get_by_label("Role of new.staff@lab.test").select_option("viewer")
    page.get_by_text("new.staff@lab.test is now viewer.").wait_for()

    me = page.locator("tr", has_text=ADMIN[0])  # the only admin cannot demote themself
    me.get_by_label(f"Role of {ADMIN[0]}").select_option("staff")
    page.get_by_role("alert").filter(has_text="this is the last active admin").wait_for()
    assert server.call("GET", "/api/v1/users/me")["role"] == "admin"
    assert watch.errors_except(r"status of (409|422)") == []


def test_admin_keeps_rigs_and_their_channel_maps(
    context: tuple, server: Server, screenshot_dir: Path
) -> None:
    ctx, watch = context
    page = open_as(ctx, server, "admin", "/admin/rigs")
    form = page.get_by_role("form", name="New rig")
    form.locator("input[name=name]").fill("EEG room 1")
    form.locator("input[name=location]").fill("B.204")
    form.locator("textarea[name=channel_map]").fill("A1 = Fp1\nA2 AF7")
    form.get_by_role("button", name="Add rig").click()
    form.get_by_text("line 2 (A2 AF7): write DEVICE = STANDARD, e.g. A1 = Fp1").wait_for()
    form.locator("textarea[name=channel_map]").fill("A1 = Fp1\nA2 = AF7\nB32 -> Cz")
    form.get_by_role("button", name="Add rig").click()
    page.get_by_text("Rig EEG room 1 added.").wait_for()
    (rig,) = [r for r in server.call("GET", "/api/v1/rigs")["items"] if r["name"] == "EEG room 1"]
    assert rig["channel_map"] == {"A1": "Fp1", "A2": "AF7", "B32": "Cz"}

    entry = page.locator(f"details[data-rig='{rig['id']}']")
    entry.locator("summary").click()
    assert "3 channels mapped" in entry.locator("summary").inner_text()
    edit = entry.get_by_role("form", name="Edit rig EEG room 1")
    edit.locator("textarea[name=channel_map]").fill("A1 = Fp1")
    edit.get_by_role("button", name="Save rig").click()
    page.get_by_text("Rig EEG room 1 saved.").wait_for()
    assert server.call("GET", f"/api/v1/rigs/{rig['id']}")["channel_map"] == {"A1": "Fp1"}
    page.locator(f"details[data-rig='{rig['id']}'] summary").click()
    page.screenshot(path=str(screenshot_dir / "admin-rigs.png"), full_page=True)
    form.locator("input[name=name]").fill("EEG room 1")  # a second rig of that name
    form.get_by_role("button", name="Add rig").click()
    form.locator("input[name=name] ~ .field-error").filter(has_text="exists").wait_for()
    assert watch.errors_except(r"status of 409", r"status of 422") == []


def test_audit_log_filters(context: tuple, server: Server, screenshot_dir: Path) -> None:
    ctx, watch = context
    server.call("POST", "/api/v1/subjects", json={"code": "AUD-1"}, role="staff")
    page = open_as(ctx, server, "admin", "/admin/audit")
    page.locator("#audit-action").fill("subject.create")
    page.get_by_role("button", name="Filter").click()
    page.wait_for_url(re.compile(r"/admin/audit\?action=subject\.create$"))
    rows = page.locator("main table tbody tr")
    expect(rows.filter(has_not_text="subject.create")).to_have_count(0)
    rows.first.wait_for()
    assert any("staff@lab.test" in text for text in rows.all_inner_texts())
    page.locator("#audit-actor").select_option(label="viewer@lab.test")
    page.get_by_text("No entries match.").wait_for()
    page.reload()  # the filters are in the address
    assert page.locator("#audit-action").input_value() == "subject.create"
    page.locator("#audit-actor").select_option("")
    page.locator("#audit-action").fill("")
    page.get_by_role("button", name="Filter").click()
    page.wait_for_url(re.compile(r"/admin/audit$"))
    page.screenshot(path=str(screenshot_dir / "admin-audit.png"), full_page=True)
    assert watch.errors_except() == []


def test_own_api_tokens_and_password(context: tuple, server: Server, screenshot_dir: Path) -> None:
    ctx, watch = context
    email, password = "pw.change@lab.test", "first-password-123"
    server.call("POST", "/api/v1/users", json={"email": email, "password": password})
    page = ctx.new_page()
    page.goto("/signin")
    page.fill("input[name=email]", email)
    page.fill("input[name=password]", password)
    page.click("button[type=submit]")
    page.get_by_role("link", name=re.compile(email)).click()  # the account link, top right
    page.wait_for_url(re.compile(r"/account$"))

    tokens = page.locator("#token-form")
    tokens.locator("input[name=name]").fill("analysis laptop")
    tokens.get_by_role("button", name="Create token").click()
    token = page.locator(".shown-once input.secret").input_value()
    assert token.startswith("bgrl_")
    assert (
        httpx.get(
            server.base_url + "/api/v1/users/me", headers={"Authorization": f"Bearer {token}"}
        ).json()["email"]
        == email
    )
    row = page.locator("tr", has_text="analysis laptop")
    assert token[:8] in row.inner_text()
    page.screenshot(path=str(screenshot_dir / "account.png"), full_page=True)
    row.get_by_role("button", name="Revoke").click()
    page.get_by_text("Token analysis laptop revoked: it stops working at once.").wait_for()
    assert (
        httpx.get(
            server.base_url + "/api/v1/users/me", headers={"Authorization": f"Bearer {token}"}
        ).status_code
        == 401
    )

    form = page.locator("#password-form")
    form.locator("input[name=current_password]").fill("not my password")
    form.locator("input[name=new_password]").fill("second-password-123")
    form.locator("input[name=repeat]").fill("second-password-123")
    form.get_by_role("button", name="Change password").click()
    form.locator("input[name=current_password] ~ .field-error").filter(
        has_text="current password is wrong"
    ).wait_for()
    form.locator("input[name=current_password]").fill(password)
    form.locator("input[name=repeat]").fill("second-password-12")
    form.get_by_role("button", name="Change password").click()
    form.get_by_text("the two new passwords differ").wait_for()
    form.locator("input[name=repeat]").fill("second-password-123")
    form.get_by_role("button", name="Change password").click()
    page.wait_for_url(re.compile(r"/signin\?next=%2Faccount$"))
    page.get_by_text("Password changed: sign in with the new one.").wait_for()
    page.fill("input[name=email]", email)
    page.fill("input[name=password]", "second-password-123")
    page.click("button[type=submit]")
    page.wait_for_url(re.compile(r"/account$"))
    assert watch.errors_except(r"status of 422") == []


def test_recordings_upload_calibrate_and_delete(
    context: tuple, server: Server, synthetic_bdf: Path, tmp_path: Path, screenshot_dir: Path
) -> None:
    ctx, watch = context
    subject = server.call("POST", "/api/v1/subjects", json={"code": "REC-1"})
    start = (datetime.now(UTC) - timedelta(days=1)).isoformat()
    session = server.call(
        "POST", "/api/v1/sessions",
        json={"subject_id": subject["id"], "kind": "calibration", "scheduled_at": start,
              "allow_past": True},  # it happened
    )  # fmt: skip
    viewer = open_as(ctx, server, "viewer", "/recordings")
    viewer.get_by_role("heading", name="Recordings").wait_for()
    assert viewer.locator("#upload-form").count() == 0
    viewer.close()

    page = open_as(ctx, server, "staff", f"/recordings?subject_id={subject['id']}")
    form = page.locator("#upload-form")
    form.locator("select[name=session_id] option").nth(1).wait_for(state="attached")
    form.locator("select[name=session_id]").select_option(str(session["id"]))
    notes = tmp_path / "notes.txt"
    notes.write_text("not EEG")
    form.locator("input[type=file]").set_input_files(str(notes))
    file_error = form.locator("#dropzone ~ .field-error")
    file_error.filter(has_text="notes.txt is not a recording the EEG service reads").wait_for()

    broken = tmp_path / "broken.bdf"
    broken.write_bytes(b"0" * 4096)
    form.locator("input[type=file]").set_input_files(str(broken))
    form.get_by_role("button", name="Upload").click()
    file_error.filter(has_text="stored, but refused by the validation:").wait_for()

    phases: list[str] = []
    page.expose_function("notePhase", lambda text: phases.append(text))
    page.evaluate(
        """() => new MutationObserver(() => window.notePhase(
            document.querySelector('#upload-phase').textContent)).observe(
            document.querySelector('#upload-phase'), {childList: true, characterData: true,
            subtree: true})"""
    )
    form.locator("input[type=file]").set_input_files(str(synthetic_bdf))
    form.get_by_role("button", name="Upload").click()
    page.get_by_text("s01.bdf uploaded: valid.").wait_for()
    assert any(p.startswith("uploading s01.bdf: ") for p in phases), phases
    assert "uploaded; the EEG service is validating it…" in phases
    recordings = server.call("GET", "/api/v1/recordings", params={"subject_id": subject["id"]})
    valid = next(r for r in recordings["items"] if r["validation_status"] == "valid")
    row = page.locator("tr", has=page.locator(f"[data-recording='{valid['id']}']"))
    assert "valid" in row.inner_text() and "synthetic" in row.inner_text()

    row.get_by_role("button", name="Calibrate…").click()
    row.locator("input[name=max_passes]").fill("0")
    row.get_by_role("button", name="Submit calibration").click()
    row.locator("input[name=max_passes] ~ .field-error").filter(has_text="1").wait_for()
    row.locator("input[name=max_passes]").fill("5")
    row.get_by_role("button", name="Submit calibration").click()
    row.get_by_text("Calibration job submitted:").wait_for()
    job_id = row.locator(".short-id").get_attribute("data-id")
    job = server.call("GET", f"/api/v1/jobs/{job_id}")
    assert (job["kind"], job["config"]["recording_id"], job["config"]["max_passes"]) == (
        "eeg_calibration", valid["id"], 5,
    )  # fmt: skip
    page.screenshot(path=str(screenshot_dir / "recordings.png"), full_page=True)
    assert page.get_by_role("button", name="Delete").count() == 0  # staff: admins delete

    admin = open_as(ctx, server, "admin", f"/recordings?recording={valid['id']}")
    admin.on("dialog", lambda dialog: dialog.accept())
    highlighted = admin.locator("tr.highlight")
    highlighted.get_by_role("button", name="Delete").click()
    admin.get_by_role("alert").filter(
        has_text=f"eeg_calibration job {job_id} (queued) uses recording {valid['id']}"
    ).wait_for()
    server.call("POST", f"/api/v1/jobs/{job_id}/cancel")
    admin.locator("tr.highlight").get_by_role("button", name="Delete").click()
    admin.get_by_text(f"Recording {valid['id']} (s01.bdf) deleted.").wait_for()
    assert watch.errors_except(r"status of (409|422)") == []


def test_a_finished_calibration_session_links_what_it_made(
    context: tuple, server: Server, screenshot_dir: Path
) -> None:
    ctx, watch = context
    subject = server.call("POST", "/api/v1/subjects", json={"code": "CAL-1"})
    start = (datetime.now(UTC) - timedelta(hours=2)).isoformat()
    session = server.call(
        "POST", "/api/v1/sessions",
        json={"subject_id": subject["id"], "kind": "calibration", "scheduled_at": start,
              "allow_past": True},  # it happened
    )  # fmt: skip
    server.call("PATCH", f"/api/v1/sessions/{session['id']}", json={"status": "running"})
    server.call("PATCH", f"/api/v1/sessions/{session['id']}", json={"status": "completed"})
    live_job = Job(kind="live_session", status="succeeded", config={"session_id": session["id"]})
    follow_up = Job(kind="eeg_calibration", status="succeeded", config={"recording_id": 1})
    live_id, follow_id = seed(server, live_job, follow_up)
    (classifier_id,) = seed(
        server, Classifier(name="CAL-1 errp", subject_id=subject["id"], job_id=follow_id)
    )
    (run_id,) = seed(
        server,
        LiveRun(session_id=session["id"], job_id=live_id, mode="calibration", status="completed",
                options={"accelerated": True}, follow_up_job_id=follow_id),
    )  # fmt: skip
    now = utcnow()
    seed(
        server,
        *[
            LiveMarker(run_id=run_id, session_id=session["id"], step=step, sim_session_id="s",
                       sim_step=step, episode=0, action=step % 3, oracle_correct=step % 2 == 0,
                       observation=[0.0], marker_ts=float(step), eeg_ts=float(step),
                       executed_at=now)
            for step in range(3)
        ],
    )  # fmt: skip
    page = open_as(ctx, server, "staff", f"/sessions/{session['id']}/live")
    page.get_by_text("Session completed: 3 actions recorded.").wait_for()
    rows = page.locator("#live-actions tr")
    rows.nth(2).wait_for()
    assert rows.locator("td.decoded").all_inner_texts() == ["not decoded (calibration)"] * 3
    links = page.locator("#live-links")
    links.get_by_role("link", name="CAL-1 errp").wait_for()
    assert links.get_by_role("link", name=f"live job {live_id[:8]}").get_attribute("href") == (
        f"/jobs/{live_id}"
    )
    assert links.get_by_role("link", name=f"job {follow_id[:8]}").count() == 1
    assert links.get_by_role("link", name="CAL-1 errp").get_attribute("href") == (
        f"/classifiers/{classifier_id}"
    )
    assert page.get_by_text("Session started.").count() == 0
    page.screenshot(path=str(screenshot_dir / "live-calibration-done.png"), full_page=True)
    assert watch.errors_except(r"status of 404", r"WebSocket") == []


def test_ids_people_can_type_and_the_schedule_forms_care(context: tuple, server: Server) -> None:
    ctx, watch = context
    ctx.grant_permissions(["clipboard-read", "clipboard-write"])
    (job_id,) = seed(
        server,
        Job(kind="guided_ppo", status="failed", config={"task": "sssg", "method": "rl_sparse"}),
    )
    page = open_as(ctx, server, "staff", "/jobs")
    cell = page.locator(f"tr[data-job='{job_id}'] .short-id").first
    assert cell.get_by_role("link").inner_text() == job_id[:8]
    cell.get_by_role("button", name=f"Copy the full id {job_id}").click()
    assert page.evaluate("navigator.clipboard.readText()") == job_id
    page.goto(f"/jobs/{job_id[:8]}")  # a short id in the address finds the job
    page.get_by_role("heading", name=f"Job {job_id[:8]} failed").wait_for()
    page.locator("table", has_text="History").get_by_text("submitted").wait_for()

    subject = server.call("POST", "/api/v1/subjects", json={"code": "PAST-1"})
    next_week = (datetime.now() + timedelta(days=7)).strftime("%G-W%V")
    page.goto(f"/sessions?week={next_week}")
    form = page.locator("#schedule-form")
    assert form.locator("input[name=time]").input_value() == "09:00"  # not 01:00
    form.locator("select[name=subject_id]").select_option(str(subject["id"]))
    form.locator("input[name=date]").fill("2020-01-01")
    form.locator("input[name=time]").fill("10:00")
    form.get_by_role("button", name="Schedule").click()
    form.locator("input[name=time] ~ .field-error").filter(
        has_text="is in the past: submit again to record a session that has happened."
    ).wait_for()
    assert (
        server.call("GET", "/api/v1/sessions", params={"subject_id": subject["id"]})["total"] == 0
    )
    form.get_by_role("button", name="Schedule in the past").click()
    page.get_by_text(
        re.compile(r"^Session \d+ scheduled for Jan 1, 2020, 10:00 .* \(in the past\)\.$")
    ).wait_for()
    (session,) = server.call("GET", "/api/v1/sessions", params={"subject_id": subject["id"]})[
        "items"
    ]
    page.locator(f"button[data-session='{session['id']}']").click()
    dialog = page.locator("dialog[open]")
    assert "null" not in dialog.inner_text()
    dialog.get_by_role("button", name="Close").click()

    form = page.locator("#schedule-form")  # the same slot again: the overlap, in local time
    form.locator("select[name=subject_id]").select_option(str(subject["id"]))
    form.locator("input[name=date]").fill("2020-01-01")
    form.locator("input[name=time]").fill("10:30")
    form.get_by_role("button", name="Schedule").click()
    form.get_by_role("button", name="Schedule in the past").click()
    alert = form.get_by_role("alert")
    alert.filter(has_text="overlaps session").wait_for()
    assert "T10:00:00" not in alert.inner_text() and "(times in " in alert.inner_text()
    assert watch.errors_except(r"status of 409", r"status of 422") == []


def _new_jobs(server: Server, kind: str, before: set[str]) -> list[dict]:
    """The jobs of ``kind`` not among ``before``."""
    jobs = server.call("GET", "/api/v1/jobs", params={"kind": kind, "limit": 500})["items"]
    return [j for j in jobs if j["id"] not in before]


def _cancel_all(server: Server, kind: str) -> None:
    """Queued jobs of ``kind`` cancelled (this module runs no worker)."""
    for job in server.call("GET", "/api/v1/jobs", params={"kind": kind})["items"]:
        if job["status"] == "queued":
            server.call("POST", f"/api/v1/jobs/{job['id']}/cancel")


def test_the_job_form_is_generated_from_the_job_kinds(
    context: tuple, server: Server, screenshot_dir: Path
) -> None:
    """The form's kinds, fields, bounds, defaults and help come from GET /api/v1/job-kinds:
    a guided-PPO run (a bound checked as the user types, HF-only fields shown for hf_sparse,
    the PPO settings folded, the API's refusal of a rule of the whole config at the field it
    names) and a BIDS export (its subject chosen by code)."""
    ctx, watch = context
    subject = server.call("POST", "/api/v1/subjects", json={"code": "FORM-1"})
    kinds = server.call("GET", "/api/v1/job-kinds", role="staff")
    before = {j["id"] for j in server.call("GET", "/api/v1/jobs", params={"limit": 500})["items"]}
    page = open_as(ctx, server, "staff", "/jobs")
    form = page.locator("#job-form")
    form.wait_for()
    offered = form.locator("select[name=kind] option").all_inner_texts()
    assert offered == [k["title"] for k in kinds if k["submittable"]]

    form.locator("select[name=method]").select_option("rl_sparse")
    accuracy = form.locator("input[name=accuracy]")
    assert accuracy.is_hidden()
    form.locator("select[name=method]").select_option("hf_sparse")
    assert accuracy.is_visible()
    hf_method = form.locator("select[name=hf_method]")
    guided = next(k for k in kinds if k["name"] == "guided_ppo")["config_schema"]
    methods = guided["properties"]["hf_method"]["anyOf"][0]["enum"]
    assert hf_method.locator("option").evaluate_all("os => os.map((o) => o.value)") == [
        "", *methods,
    ]  # fmt: skip
    assert form.locator("input[name=total_steps]").input_value() == "40000"  # its default
    form.locator("input[name=total_steps]").fill("0")
    assert form.locator("input[name=total_steps] ~ .field-error").inner_text() == (
        "must be between 1 and 2,000,000"
    )
    form.locator("input[name=total_steps]").fill("1024")
    accuracy.fill("0.7")
    ppo = form.locator("details[data-field=ppo]")
    assert form.locator("input[name='ppo.n_steps']").is_hidden()  # folded
    ppo.locator("summary").click()
    form.locator("input[name='ppo.n_steps']").fill("100")
    form.get_by_role("button", name="Submit job").click()
    form.locator("input[name='ppo.n_steps'] ~ .field-error").filter(
        has_text="n_steps (100) must be a multiple of minibatch_size (64)"
    ).wait_for()
    assert _new_jobs(server, "guided_ppo", before) == []
    form.locator("input[name='ppo.n_steps']").fill("128")
    form.get_by_role("button", name="Submit job").click()
    page.get_by_text(re.compile(r"^Job \w{8} submitted\.$")).wait_for()
    ppo.locator("summary").click()  # folded again for the screenshot
    (job,) = _new_jobs(server, "guided_ppo", before)
    assert job["config"] == {
        "task": "sssg", "method": "hf_sparse", "accuracy": 0.7, "seed": 0, "total_steps": 1024,
        "hf_treatment": "authors", "ppo": {"n_steps": 128}, "preset": "paper",
        "n_labels": 1000,
    }  # fmt: skip
    page.screenshot(path=str(screenshot_dir / "jobs-form.png"), full_page=True)
    _cancel_all(server, "guided_ppo")

    form.locator("select[name=kind]").select_option("bids_export")
    form.get_by_role("button", name="Submit job").click()
    assert form.locator("select[name=subject_id] ~ .field-error").inner_text() == "required"
    form.locator("select[name=subject_id]").select_option(label=f"#{subject['id']} FORM-1")
    form.get_by_role("button", name="Submit job").click()
    form.get_by_role("link", name="follow it").wait_for()
    (export,) = _new_jobs(server, "bids_export", before)
    assert export["config"] == {"subject_id": subject["id"]}
    _cancel_all(server, "bids_export")
    assert watch.errors_except(r"status of 422") == []


def test_a_finished_online_session_is_replayed_from_its_page(
    context: tuple, server: Server, screenshot_dir: Path
) -> None:
    """The replay link of an ended online session opens the generated form with the kind
    chosen and the session filled in; a bound and an unknown id are refused at their
    fields; the submitted job is followed on its page."""
    ctx, watch = context
    subject = server.call("POST", "/api/v1/subjects", json={"code": "REPLAY-1"})
    start = (datetime.now(UTC) - timedelta(hours=3)).isoformat()
    session = server.call(
        "POST", "/api/v1/sessions",
        json={"subject_id": subject["id"], "kind": "online", "scheduled_at": start,
              "allow_past": True},
    )  # fmt: skip
    server.call("PATCH", f"/api/v1/sessions/{session['id']}", json={"status": "running"})
    server.call("PATCH", f"/api/v1/sessions/{session['id']}", json={"status": "completed"})
    (live_id,) = seed(
        server, Job(kind="live_session", status="succeeded", config={"session_id": session["id"]})
    )
    (classifier_id,) = seed(server, Classifier(name="REPLAY-1 errp", subject_id=subject["id"]))
    seed(
        server,
        LiveRun(session_id=session["id"], job_id=live_id, mode="online", status="completed",
                options={"accelerated": True, "classifier_id": classifier_id}),
    )  # fmt: skip
    page = open_as(ctx, server, "staff", f"/sessions/{session['id']}/live")
    page.get_by_role("link", name="Replay this session…").click()
    form = page.locator("#job-form")
    assert form.locator("select[name=kind]").input_value() == "session_replay"
    assert form.locator("input[name=session_id]").input_value() == str(session["id"])
    form.locator("select[name=classifier_id]").select_option(str(classifier_id))
    form.locator("input[name=label_budget]").fill("0")
    assert form.locator("input[name=label_budget] ~ .field-error").inner_text() == (
        "must be between 1 and 100,000"
    )
    form.locator("input[name=label_budget]").fill("50")
    form.locator("input[name=session_id]").fill("999999")
    form.get_by_role("button", name="Submit job").click()
    form.locator("input[name=session_id] ~ .field-error").filter(
        has_text="no session with id 999999"
    ).wait_for()
    form.locator("input[name=session_id]").fill(str(session["id"]))
    form.get_by_role("button", name="Submit job").click()
    follow = form.get_by_role("link", name="follow it")
    follow.wait_for()
    page.screenshot(path=str(screenshot_dir / "job-replay.png"), full_page=True)
    follow.click()
    page.get_by_role("heading", name=re.compile(r"^Job \w{8} queued$")).wait_for()
    (job,) = server.call("GET", "/api/v1/jobs", params={"kind": "session_replay"})["items"]
    assert page.url.endswith(f"/jobs/{job['id']}")
    assert job["config"] == {
        "session_id": session["id"], "classifier_id": classifier_id, "label_budget": 50,
    }  # fmt: skip
    _cancel_all(server, "session_replay")
    assert watch.errors_except(r"status of (404|422)", r"WebSocket") == []


def test_a_reschedule_into_the_past_is_confirmed_first(context: tuple, server: Server) -> None:
    """The API refuses a start in the past until the request confirms it; the dashboard asks
    at the start field and sends ``allow_past`` only once the user has confirmed."""
    ctx, watch = context
    subject = server.call("POST", "/api/v1/subjects", json={"code": "PAST-2"})
    start = datetime.now(UTC).replace(microsecond=0) + timedelta(days=1)
    session = server.call(
        "POST", "/api/v1/sessions",
        json={"subject_id": subject["id"], "kind": "test", "scheduled_at": start.isoformat()},
    )  # fmt: skip
    page = open_as(ctx, server, "staff", f"/sessions?week={start.astimezone():%G-W%V}")
    sent: list[dict] = []
    page.on(
        "request",
        lambda r: sent.append(r.post_data_json) if r.method == "PATCH" else None,
    )
    page.locator(f"button[data-session='{session['id']}']").click()
    dialog = page.locator("dialog[open]")
    dialog.locator("input[name=date]").fill("2020-01-01")
    dialog.locator("input[name=time]").fill("10:00")
    dialog.get_by_role("button", name="Reschedule").click()
    dialog.locator("input[name=time] ~ .field-error").filter(
        has_text="is in the past: submit again to record a session that has happened."
    ).wait_for()
    assert server.call("GET", f"/api/v1/sessions/{session['id']}")["scheduled_at"] == (
        start.isoformat().replace("+00:00", "Z")
    )
    dialog.get_by_role("button", name="Reschedule in the past").click()
    page.get_by_text(f"Session {session['id']} rescheduled.").wait_for()
    moved = server.call("GET", f"/api/v1/sessions/{session['id']}")
    assert (
        datetime.fromisoformat(moved["scheduled_at"]).astimezone().strftime("%Y-%m-%d %H:%M")
        == "2020-01-01 10:00"
    )
    assert [body["allow_past"] for body in sent] == [False, True]
    assert watch.errors_except(r"status of 422") == []
