"""The dashboard in Chromium: sign in and out, roles, subjects, sessions with a refused
conflict, a job's live progress to the end with its curve and model download, every page
free of console errors and of requests off 127.0.0.1 (checked by the ``context`` fixture)."""

from __future__ import annotations

import json
import re
import zipfile
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from services.core.db.models import Classifier, Job
from services.core.db.session import make_engine, make_session_factory
from services.core.hf_methods import HF_METHOD_NAMES
from services.core.platform import PlatformSettings
from tests.web.conftest import STAFF, Server, open_as

pytestmark = pytest.mark.slow

NAV = ["Subjects", "Sessions", "Jobs", "Recordings", "Models"]
"""The navigation of staff and viewers (admins also get Users, Rigs, Audit)."""
TINY_PPO = {"n_epochs": 4, "eval_every": 256}


def nav_labels(page) -> list[str]:
    return page.locator("nav[aria-label=Main] a").all_inner_texts()


def test_sign_in_wrong_password_then_right_then_out(context: tuple, server: Server) -> None:
    ctx, watch = context
    page = ctx.new_page()
    page.goto("/jobs")
    page.wait_for_url(re.compile(r"/signin\?next=%2Fjobs$"))
    page.fill("input[name=email]", STAFF[0])
    page.fill("input[name=password]", "not-the-password")
    page.click("button[type=submit]")
    alert = page.get_by_role("alert")
    alert.wait_for()
    assert alert.inner_text() == "wrong e-mail or password, or account deactivated"
    page.fill("input[name=password]", STAFF[1])
    page.click("button[type=submit]")
    page.wait_for_url(re.compile(r"/jobs$"))
    # the account box is drawn once /users/me answered; until then the admin links are in
    # the page, hidden (their text would count): read the nav after it
    assert page.locator("#account .who").inner_text() == f"{STAFF[0]} staff"
    assert nav_labels(page) == NAV
    assert page.locator("nav a[aria-current=page]").inner_text() == "Jobs"
    page.get_by_role("button", name="Sign out").click()
    page.wait_for_url(re.compile(r"/signin$"))
    page.goto("/subjects")
    page.wait_for_url(re.compile(r"/signin\?next="))
    assert watch.errors_except(r"status of 401") == []


def test_viewer_is_offered_no_changes(context: tuple, server: Server) -> None:
    ctx, watch = context
    subject = server.call("POST", "/api/v1/subjects", json={"code": "V-01", "notes": "read only"})
    server.call(
        "POST",
        "/api/v1/sessions",
        json={"subject_id": subject["id"], "kind": "online",
              "scheduled_at": (datetime.now(UTC) + timedelta(days=3)).isoformat()},
    )  # fmt: skip
    page = open_as(ctx, server, "viewer", "/subjects")
    page.get_by_role("link", name="V-01").wait_for()
    assert page.locator("form", has_text="New subject").count() == 0
    page.goto(f"/subjects/{subject['id']}")
    page.get_by_role("heading", name="Subject V-01").wait_for()
    assert page.locator("textarea").count() == 0
    assert page.get_by_role("link", name="Live view").count() == 0  # none started
    assert page.get_by_role("button", name="Save notes").count() == 0
    page.goto("/sessions")
    page.locator("table.week").wait_for()
    assert page.locator("#schedule-form").count() == 0
    page.goto("/jobs")
    page.locator("#jobs-table").wait_for()
    assert page.locator("#job-form").count() == 0
    assert watch.console_errors == []


def test_create_subject_search_and_edit_notes(context: tuple, server: Server) -> None:
    ctx, watch = context
    page = open_as(ctx, server, "staff", "/subjects")
    page.fill("#new-subject-code", "bad code!")
    assert "starts with a letter or digit" in page.locator(".field-error").first.inner_text()
    page.fill("#new-subject-code", "S-web-01")
    page.fill("textarea[name=notes]", "first visit")
    page.get_by_role("button", name="Create subject").click()
    page.get_by_text("Subject S-web-01 created.").wait_for()
    page.get_by_role("link", name="S-web-01").wait_for()
    page.fill("#subject-search", "S-web")
    page.wait_for_function(
        "() => [...document.querySelectorAll('table.grid tbody a')].map(a => a.textContent)"
        ".join() === 'S-web-01'"
    )
    page.get_by_role("link", name="S-web-01").click()
    page.get_by_role("heading", name="Subject S-web-01").wait_for()
    page.fill("textarea[name=notes]", "first visit; prefers mornings")
    page.get_by_role("button", name="Save notes").click()
    page.get_by_text("Notes saved.").wait_for()
    subjects = server.call("GET", "/api/v1/subjects", params={"code": "S-web-01"})["items"]
    assert [(s["code"], s["notes"]) for s in subjects] == [
        ("S-web-01", "first visit; prefers mornings")
    ]
    assert watch.console_errors == []


def test_schedule_conflict_reschedule_cancel(context: tuple, server: Server) -> None:
    ctx, watch = context
    subject = server.call("POST", "/api/v1/subjects", json={"code": "S-sched"})
    rig = server.call("POST", "/api/v1/rigs", json={"name": "Rig A", "location": "room 2"})
    start = (datetime.now(UTC) + timedelta(days=1)).astimezone()  # browser runs in this zone
    day, time = start.strftime("%Y-%m-%d"), "10:00"
    page = open_as(ctx, server, "staff", "/sessions")
    form = page.locator("#schedule-form")

    def schedule(minutes: int) -> None:
        form.locator("select[name=subject_id]").select_option(str(subject["id"]))
        form.locator("select[name=kind]").select_option("calibration")
        form.locator("select[name=rig_id]").select_option(str(rig["id"]))
        form.locator("input[name=date]").fill(day)
        form.locator("input[name=time]").fill(time)
        form.locator("input[name=duration_minutes]").fill(str(minutes))
        form.get_by_role("button", name="Schedule").click()

    schedule(60)
    page.get_by_text(re.compile(r"^Session \d+ scheduled for")).wait_for()
    sessions = server.call("GET", "/api/v1/sessions", params={"subject_id": subject["id"]})
    (first,) = sessions["items"]
    slot = page.locator(f"button[data-session='{first['id']}']")
    assert slot.inner_text().split("\n")[0].endswith("S-sched calibration")
    row = page.locator("table.week tbody tr", has_text="Rig A")
    assert row.locator(f"button[data-session='{first['id']}']").count() == 1

    schedule(30)  # same subject, same rig, same start: refused
    alert = form.get_by_role("alert")
    alert.wait_for()
    assert alert.inner_text().startswith(f"overlaps session {first['id']} of the same subject (")
    assert (
        server.call("GET", "/api/v1/sessions", params={"subject_id": subject["id"]})["total"] == 1
    )

    slot.click()
    dialog = page.locator("dialog[open]")
    live = dialog.get_by_role("link", name="Live view")  # staff start it there
    assert live.get_attribute("href") == f"/sessions/{first['id']}/live"
    dialog.locator("input[name=time]").fill("14:30")
    dialog.get_by_role("button", name="Reschedule").click()
    page.get_by_text(f"Session {first['id']} rescheduled.").wait_for()
    moved = server.call("GET", f"/api/v1/sessions/{first['id']}")
    local = datetime.fromisoformat(moved["scheduled_at"]).astimezone()
    assert local.strftime("%Y-%m-%d %H:%M") == f"{day} 14:30"

    page.locator(f"button[data-session='{first['id']}']").click()
    page.locator("dialog[open]").get_by_role("button", name="Cancel session").click()
    page.get_by_text(f"Session {first['id']} cancelled.").wait_for()
    assert server.call("GET", f"/api/v1/sessions/{first['id']}")["status"] == "cancelled"
    assert "status-cancelled" in page.locator(
        f"button[data-session='{first['id']}']"
    ).get_attribute("class")
    assert watch.errors_except(r"status of 409 \(Conflict\)") == []


def test_job_form_validates_as_the_user_types(context: tuple, server: Server) -> None:
    """The generated form checks each field against its kind's schema as the user types;
    a rule of the whole config (a sweep's run count) is the API's, shown in the form."""
    ctx, watch = context
    page = open_as(ctx, server, "staff", "/jobs")
    form = page.locator("#job-form")
    form.locator("input[name=total_steps]").fill("0")
    assert form.locator("input[name=total_steps] ~ .field-error").inner_text() == (
        "must be between 1 and 2,000,000"
    )
    form.locator("input[name=total_steps]").fill("1024")
    assert form.locator("input[name=total_steps] ~ .field-error").inner_text() == ""
    form.locator("select[name=method]").select_option("hf_sparse")
    form.locator("input[name=accuracy]").fill("1.5")
    assert form.locator("input[name=accuracy] ~ .field-error").inner_text() == (
        "must be between 0 and 1"
    )
    form.locator("select[name=kind]").select_option("reproduce")
    form.locator("input[name=seeds]").fill("101")
    assert form.locator("input[name=seeds] ~ .field-error").inner_text() == (
        "must be between 1 and 100"
    )
    form.locator("input[name=accuracies]").fill("0.5, 1.5")
    assert form.locator("input[name=accuracies] ~ .field-error").inner_text() == (
        "each value must be between 0 and 1: not 1.5"
    )
    for task in ("sssg", "vssg"):
        form.locator(f"input[name=tasks][value={task}]").uncheck()
    assert form.locator("fieldset:has(input[name=tasks]) ~ .field-error").inner_text() == (
        "choose at least 1"
    )
    form.locator("input[name=tasks][value=sssg]").check()
    form.locator("input[name=seeds]").fill("100")
    form.locator("input[name=accuracies]").fill("0.5, 0.55, 0.6, 0.7, 0.8, 0.9")
    form.locator("input[name=tasks][value=vssg]").check()
    form.locator("input[name=treatments][value=truncated_is]").check()
    form.get_by_role("button", name="Submit job").click()
    form.get_by_role("alert").filter(has_text="2800 runs; a reproduce job may have 2000").wait_for()
    assert server.call("GET", "/api/v1/jobs", params={"kind": "reproduce"})["total"] == 0
    assert watch.errors_except(r"status of 422") == []


def test_chart_statistics_are_mean_and_half_std(context: tuple, server: Server) -> None:
    ctx, _ = context
    page = ctx.new_page()
    page.goto("/signin")
    stats = page.evaluate(
        """async () => {
            const { meanHalfStd } = await import('/assets/js/chart.js');
            return meanHalfStd([[[0, 0.25], [256, 0.5], [512, 1.0]], [[0, 0.75], [256, 0.5]]]);
        }"""
    )
    assert stats == {"points": [[0, 0.5], [256, 0.5]], "band": [[0, 0.375, 0.625], [256, 0.5, 0.5]]}


def test_job_progress_reaches_the_end_and_model_downloads(
    context: tuple, server: Server, screenshot_dir: Path, tmp_path: Path
) -> None:
    ctx, watch = context
    page = open_as(ctx, server, "staff", "/jobs")
    form = page.locator("#job-form")
    form.locator("select[name=task]").select_option("sssg")
    form.locator("select[name=method]").select_option("rl_sparse")
    form.locator("input[name=seed]").fill("3")
    form.locator("input[name=total_steps]").fill("1024")
    form.locator("details[data-field=ppo] summary").click()
    form.locator("input[name='ppo.n_epochs']").fill(str(TINY_PPO["n_epochs"]))
    form.locator("input[name='ppo.eval_every']").fill(str(TINY_PPO["eval_every"]))
    form.get_by_role("button", name="Submit job").click()
    page.get_by_text(re.compile(r"^Job \w{8} submitted\.$")).wait_for()
    (job,) = server.call("GET", "/api/v1/jobs", params={"kind": "guided_ppo"})["items"]
    assert job["config"] == {
        "task": "sssg", "method": "rl_sparse", "seed": 3, "total_steps": 1024,
        "hf_treatment": "authors", "ppo": TINY_PPO, "n_labels": 1000, "preset": "paper",
    }  # fmt: skip
    bar = page.locator(f"tr[data-job='{job['id']}'] progress")
    bar.wait_for()
    page.evaluate(
        """(sel) => {
            const bar = document.querySelector(sel);
            window.progressSeen = [bar.value];
            new MutationObserver(() => window.progressSeen.push(bar.value))
                .observe(bar, { attributes: true });
        }""",
        f"tr[data-job='{job['id']}'] progress",
    )
    page.wait_for_function(
        "(sel) => document.querySelector(sel).dataset.status === 'succeeded'",
        arg=f"tr[data-job='{job['id']}'] progress",
        timeout=120_000,
    )
    assert bar.evaluate("b => b.value") == 1.0
    assert page.locator(f"tr[data-job='{job['id']}'] .pct").inner_text() == "100%"
    seen = page.evaluate("window.progressSeen")
    assert seen == sorted(seen) and seen[-1] == 1.0  # it only moved forward
    assert len(set(seen)) >= 3  # pushed live, not only at the start and the end
    page.screenshot(path=str(screenshot_dir / "jobs-finished.png"), full_page=True)

    page.get_by_role("link", name=job["id"][:8]).click()
    page.locator("svg.chart polyline").first.wait_for(state="attached")
    points = page.locator("svg.chart polyline").first.get_attribute("points").split()
    assert len(points) == 5  # evaluations at 0, 256, 512, 768, 1024 steps
    page.wait_for_function(
        "() => { const i = document.querySelector('img.plot'); return i && i.naturalWidth > 0; }"
    )
    assert page.locator("img.plot").evaluate("i => [i.naturalWidth, i.naturalHeight]") == [600, 350]
    page.screenshot(path=str(screenshot_dir / "job.png"), full_page=True)

    with page.expect_download() as info:
        page.get_by_role("button", name="Download model").click()
    download = info.value
    assert download.suggested_filename == f"policy-{job['id']}.pt"
    saved = tmp_path / download.suggested_filename
    download.save_as(saved)
    assert zipfile.is_zipfile(saved)  # TorchScript archives are zip files
    page.get_by_text(re.compile(r"SHA-256 verified")).first.wait_for()

    with page.expect_download() as info:
        page.get_by_role("button", name="JSON").click()
    curve = json.loads(Path(info.value.path()).read_text())
    assert [step for step, _ in curve["curve"]] == [0, 256, 512, 768, 1024]
    assert watch.console_errors == []


def test_cancel_and_retry_from_the_list(context: tuple, server: Server) -> None:
    ctx, watch = context
    config = {"task": "vssg", "method": "rl_sparse", "seed": 9, "total_steps": 200_000}
    job = server.call("POST", "/api/v1/jobs", json={"kind": "guided_ppo", "config": config})
    page = open_as(ctx, server, "staff", "/jobs")
    row = page.locator(f"tr[data-job='{job['id']}']")
    assert job["summary"] == "VSSG rl_sparse seed 9, 200,000 steps"
    row.get_by_role("cell", name=job["summary"], exact=True).wait_for()  # the API's line
    row.get_by_role("button", name="Cancel").click()
    page.get_by_text(f"Cancel requested for job {job['id'][:8]}.").wait_for()
    row.locator(".badge", has_text="cancelled").wait_for(timeout=30_000)
    assert row.get_by_role("button", name="Cancel").count() == 0
    row.get_by_role("button", name="Retry").click()
    page.get_by_text(f"Job {job['id'][:8]} queued again.").wait_for()
    assert server.call("GET", f"/api/v1/jobs/{job['id']}")["status"] in ("queued", "running")
    row.get_by_role("button", name="Cancel").click()  # and stop it again
    row.locator(".badge", has_text="cancelled").wait_for(timeout=30_000)
    assert server.call("GET", f"/api/v1/jobs/{job['id']}")["status"] == "cancelled"
    assert watch.console_errors == []


def test_job_form_sends_the_stage2_method_and_the_preset(context: tuple, server: Server) -> None:
    ctx, watch = context
    page = open_as(ctx, server, "staff", "/jobs")
    form = page.locator("#job-form")
    hf_method = form.locator("select[name=hf_method]")
    form.locator("select[name=method]").select_option("rl_sparse")
    assert hf_method.is_hidden()
    form.locator("select[name=method]").select_option("hf_sparse")
    options = hf_method.locator("option").evaluate_all("os => os.map((o) => o.value)")
    assert options == ["", *HF_METHOD_NAMES]  # "": the recommended method
    hf_method.select_option("noise_aware")
    form.locator("input[name=accuracy]").fill("0.7")
    form.locator("select[name=preset]").select_option("platform")
    form.locator("input[name=seed]").fill("5")
    form.locator("input[name=total_steps]").fill("256")
    form.locator("input[name=n_labels]").fill("50")
    form.get_by_role("button", name="Submit job").click()
    page.get_by_text(re.compile(r"^Job \w{8} submitted\.$")).wait_for()
    jobs = server.call("GET", "/api/v1/jobs", params={"kind": "guided_ppo"})["items"]
    (job,) = [j for j in jobs if j["config"].get("hf_method")]
    server.call("POST", f"/api/v1/jobs/{job['id']}/cancel")
    assert job["config"] == {
        "task": "sssg", "method": "hf_sparse", "accuracy": 0.7, "seed": 5, "total_steps": 256,
        "hf_treatment": "authors", "ppo": {}, "n_labels": 50, "hf_method": "noise_aware",
        "preset": "platform",
    }  # fmt: skip

    page.reload()
    form.locator("select[name=kind]").select_option("reproduce")
    form.locator("input[name=seeds]").fill("1")
    form.locator("input[value=vssg]").uncheck()
    form.locator("input[value=rl_rich]").uncheck()
    form.locator("input[value=hf_sparse]").uncheck()
    form.locator("details[data-field=ppo] summary").click()
    form.locator("input[name='ppo.total_steps']").fill("256")
    form.locator("select[name=preset]").select_option("platform")
    form.locator("input[name=n_labels]").fill("0")
    form.get_by_text("must be between 1 and 1,000,000").wait_for()
    form.get_by_role("button", name="Submit job").click()
    form.get_by_role("alert").filter(has_text="Correct the fields marked above.").wait_for()
    form.locator("input[name=n_labels]").fill("4000")
    form.get_by_role("button", name="Submit job").click()
    page.get_by_text(re.compile(r"^Job \w{8} submitted\.$")).wait_for()
    (sweep,) = server.call("GET", "/api/v1/jobs", params={"kind": "reproduce"})["items"]
    server.call("POST", f"/api/v1/jobs/{sweep['id']}/cancel")
    config = sweep["config"]
    assert (config["preset"], config["methods"], config["n_labels"]) == (
        "platform", ["rl_sparse"], 4000,
    )  # fmt: skip
    assert watch.console_errors == []


RUNS = {  # (method, accuracy, seed): (curve, SPL of pi_HF); binary-exact values
    ("rl_sparse", None, 0): ([[0, 0.0], [256, 0.25], [512, 0.5]], None),
    ("rl_sparse", None, 1): ([[0, 0.0], [256, 0.75], [512, 1.0]], None),
    ("hf_sparse", 0.7, 0): ([[0, 0.5], [256, 0.5], [512, 1.0]], 0.5),
    ("hf_sparse", 0.7, 1): ([[0, 0.5], [256, 1.0], [512, 1.0]], 1.0),
}


def test_reproduction_shows_mean_half_std_and_hf_lines(
    context: tuple, server: Server, screenshot_dir: Path
) -> None:
    """A finished reproduction's runs (rows as its workers leave them) drawn as Fig. 3."""
    engine = make_engine(PlatformSettings(data_dir=server.root / "data").resolved_database_url)
    with make_session_factory(engine)() as db:
        parent = Job(
            kind="reproduce",
            config={"tasks": ["sssg"], "methods": ["rl_sparse", "hf_sparse"], "seeds": 2,
                    "accuracies": [0.7], "treatments": ["authors"]},
            status="succeeded", progress=1.0, attempts=1,
            result={"runs": 4, "succeeded": 4, "failed": [], "artifacts": {}, "claims": []},
        )  # fmt: skip
        db.add(parent)
        db.flush()
        for (method, accuracy, seed), (curve, hf_spl) in RUNS.items():
            config = {"task": "sssg", "method": method, "accuracy": accuracy, "seed": seed,
                      "hf_treatment": "authors" if accuracy else None}  # fmt: skip
            result = {**config, "curve": curve, "hf_policy_spl": hf_spl, "final_spl": curve[-1][1]}
            db.add(
                Job(kind="reproduce_run", config=config, parent_id=parent.id, status="succeeded",
                    progress=1.0, steps_done=512, attempts=1, curve=curve, result=result)
            )  # fmt: skip
        db.commit()
        parent_id = parent.id
    engine.dispose()
    page = open_as(context[0], server, "viewer", f"/jobs/{parent_id}")
    page.locator("svg.chart").wait_for()
    assert page.locator(".legend li").all_inner_texts() == [
        "rl_sparse (2 seeds)",
        "hf_sparse C=0.7 (2 seeds)",
        "π_HF hf_sparse C=0.7",
    ]
    lines = page.locator("svg.chart polyline")
    # x: 52 + step / 512 * 572; y: 276 - SPL * 248
    assert lines.nth(0).get_attribute("points") == "52,276 338,152 624,90"  # means 0, .5, .75
    assert lines.nth(1).get_attribute("points") == "52,152 338,90 624,28"  # means .5, .75, 1
    assert lines.nth(2).get_attribute("points") == "52,90 624,90"  # pi_HF mean 0.75, dashed
    assert lines.nth(2).get_attribute("class") == "line series-1 dashed"  # hf_sparse's colour
    band = page.locator("svg.chart path.band").first.get_attribute("d")
    assert band == "M52,276L338,121L624,59L624,121L338,183L52,276Z"  # mean ± ½ std
    assert page.get_by_text("4 of 4 run(s) finished.").count() == 1
    assert page.locator("#job-form, button:has-text('Retry')").count() == 0
    page.screenshot(path=str(screenshot_dir / "reproduction.png"), full_page=True)
    assert context[1].console_errors == []


@pytest.mark.parametrize("context", ["light", "dark"], indirect=True)
def test_every_page_is_clean_and_local(
    context: tuple, server: Server, screenshot_dir: Path, request: pytest.FixtureRequest
) -> None:
    ctx, watch = context
    scheme = request.node.callspec.params["context"]
    subject = server.call("POST", "/api/v1/subjects", json={"code": f"S-pages-{scheme}"})
    start = datetime.now(UTC).replace(minute=0, second=0, microsecond=0) + timedelta(hours=2)
    server.call(
        "POST",
        "/api/v1/sessions",
        json={"subject_id": subject["id"], "kind": "rl", "scheduled_at": start.isoformat()},
    )
    online = server.call(
        "POST",
        "/api/v1/sessions",
        json={"subject_id": subject["id"], "kind": "online",
              "scheduled_at": (start + timedelta(hours=2)).isoformat()},
    )  # fmt: skip
    engine = make_engine(PlatformSettings(data_dir=server.root / "data").resolved_database_url)
    with make_session_factory(engine)() as db:
        metrics = {"test_accuracy": 0.9, "balanced_accuracy": 0.875, "roc_auc": 0.95,
                   "confusion_matrix": [[40, 2], [3, 15]], "n_epochs": 300}  # fmt: skip
        classifier = Classifier(
            name="S-pages.bdf (seed 0)", subject_id=subject["id"], metrics=metrics
        )
        db.add(classifier)
        db.commit()
        classifier_id = classifier.id
    engine.dispose()
    page = open_as(ctx, server, "staff", "/subjects")
    pages = {
        "subjects": ("/subjects", "Subjects"),
        "subject": (f"/subjects/{subject['id']}", f"Subject S-pages-{scheme}"),
        "sessions": ("/sessions", "Sessions"),
        "jobs": ("/jobs", "Jobs"),
        "models": ("/models", "Models and downloads"),
        "classifier": (f"/classifiers/{classifier_id}", "Calibration: S-pages.bdf (seed 0)"),
        # not started: the start form, and no polling of a run that does not exist yet
        "live-start": (f"/sessions/{online['id']}/live", f"Session {online['id']} live (online)"),
    }
    for name, (path, heading) in pages.items():
        page.goto(path)
        page.get_by_role("heading", name=heading, exact=True).wait_for()
        page.wait_for_load_state("networkidle")
        assert nav_labels(page) == NAV
        suffix = "" if scheme == "light" else "-dark"
        page.screenshot(path=str(screenshot_dir / f"{name}{suffix}.png"), full_page=True)
    form = page.get_by_role("form", name="Start the session")
    assert form.get_by_label("Classifier").input_value() == str(classifier_id)
    page.goto(f"/classifiers/{classifier_id}")
    page.locator("table.confusion").wait_for()
    cells = page.locator("table.confusion tbody td").all_inner_texts()
    assert cells == ["40", "2", "3", "15"]
    page.goto(f"/sessions/{online['id']}/display")  # waits for the session to start
    page.locator("#display-frame").wait_for(state="attached")
    page.wait_for_load_state("networkidle")
    page.goto("/signin")
    page.locator("input[name=email]").wait_for()
    page.screenshot(path=str(screenshot_dir / f"signin{'' if scheme == 'light' else '-dark'}.png"))
    assert watch.console_errors == []


def test_keyboard_reaches_the_nav_and_forms(context: tuple, server: Server) -> None:
    ctx, _ = context
    page = ctx.new_page()
    page.goto("/signin")
    page.locator("input[name=email]").wait_for()
    assert page.evaluate("document.activeElement.name") == "email"
    page.keyboard.type(STAFF[0])
    page.keyboard.press("Tab")
    page.keyboard.type(STAFF[1])
    page.keyboard.press("Enter")
    page.wait_for_url(re.compile(r"/subjects$"))
    page.locator("#account button").wait_for()
    page.keyboard.press("Tab")  # the skip link comes first
    assert page.evaluate("document.activeElement.textContent") == "Skip to content"
    seen = []
    for _ in range(7):
        page.keyboard.press("Tab")
        seen.append(page.evaluate("document.activeElement.textContent"))
    assert seen[1:6] == NAV
