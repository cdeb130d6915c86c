"""What people type and send carelessly: short job ids, JSON without its Content-Type, a
JSON sign-in, a code or e-mail that fails its pattern; and what they read back: a job's
log, the curve PNG with pi_HF's line."""

from __future__ import annotations

import io

import numpy as np
from PIL import Image

from services.api.plots import curve_png
from services.core.db.models import Job
from tests.api.conftest import Api
from tests.api.test_jobs import GUIDED, set_job, submit


def _add_jobs(api: Api, *ids: str) -> None:
    with api.client.app.state.sessions() as db:
        for job_id in ids:
            db.add(Job(id=job_id, kind="guided_ppo", config=GUIDED, status="failed"))
        db.commit()


def test_a_unique_prefix_of_six_or_more_characters_names_a_job(api: Api) -> None:
    staff = api.as_("staff")
    _add_jobs(api, "abcdef01" + "0" * 24, "abcdef02" + "0" * 24, "9c7052e6" + "1" * 24)
    got = api.client.get("/api/v1/jobs/9c7052", headers=staff)
    assert got.status_code == 200, got.text
    assert got.json()["id"] == "9c7052e6" + "1" * 24
    assert api.client.get("/api/v1/jobs/9C7052E6", headers=staff).status_code == 200
    retried = api.client.post("/api/v1/jobs/9c7052e6/retry", headers=staff)
    assert retried.status_code == 200, retried.text
    assert retried.json()["status"] == "queued"
    cancelled = api.client.post("/api/v1/jobs/9c7052e6/cancel", headers=staff)
    assert cancelled.json()["status"] == "cancelled"

    ambiguous = api.client.get("/api/v1/jobs/abcdef", headers=staff)
    assert ambiguous.status_code == 409
    assert ambiguous.json()["field"] == "job_id"
    detail = ambiguous.json()["detail"]
    assert "abcdef01" + "0" * 24 in detail and "abcdef02" + "0" * 24 in detail
    assert "give more characters" in detail
    assert api.client.get("/api/v1/jobs/abcdef02", headers=staff).status_code == 200

    short = api.client.get("/api/v1/jobs/9c705", headers=staff)
    assert short.status_code == 404
    assert short.json()["detail"] == "no job with id 9c705 (give at least 6 characters of it)"
    none = api.client.get("/api/v1/jobs/fedcba98", headers=staff)
    assert none.status_code == 404
    assert none.json()["detail"] == "no job with an id starting fedcba98"
    wildcard = api.client.get("/api/v1/jobs/abcde%25", headers=staff)  # LIKE's % is no wildcard
    assert wildcard.status_code == 404


def test_a_jobs_log_says_who_did_what_and_how_it_ended(api: Api) -> None:
    job_id = submit(api, "guided_ppo", GUIDED).json()["id"]
    api.client.post(f"/api/v1/jobs/{job_id}/cancel", headers=api.as_("staff"))
    api.client.post(f"/api/v1/jobs/{job_id[:8]}/retry", headers=api.as_("staff"))
    log = api.client.get(f"/api/v1/jobs/{job_id[:6]}/log", headers=api.as_("viewer"))
    assert log.status_code == 200, log.text
    events = [(e["event"], e["actor_email"]) for e in log.json()["items"]]
    assert events == [
        ("submitted", "staff@lab.test"),
        ("cancel requested", "staff@lab.test"),
        ("retried", "staff@lab.test"),
    ]
    assert log.json()["job_id"] == job_id


def test_the_log_of_a_failed_job_ends_with_its_error(api: Api) -> None:
    job_id = submit(api, "guided_ppo", GUIDED).json()["id"]
    from services.core.db.base import utcnow

    set_job(api, job_id, status="failed", error="out of memory", attempts=3, finished_at=utcnow())
    set_job(api, job_id, started_at=utcnow().replace(year=2000), resumed_from_step=512)
    items = api.client.get(f"/api/v1/jobs/{job_id}/log", headers=api.as_("viewer")).json()["items"]
    assert [e["event"] for e in items] == ["started", "submitted", "failed"]
    assert items[0]["detail"] == "attempt 3 of 3, resumed from step 512"
    assert items[-1]["detail"] == "out of memory"


def test_json_without_its_content_type_is_answered_in_words(api: Api) -> None:
    body = b'{"code": "S01"}'
    sent = api.client.post(
        "/api/v1/subjects",
        content=body,
        headers={**api.as_("staff"), "Content-Type": "application/x-www-form-urlencoded"},
    )
    assert sent.status_code == 422
    message = sent.json()["message"]
    assert "must be JSON sent with Content-Type: application/json" in message
    assert "application/x-www-form-urlencoded" in message
    assert "valid dictionary" not in message
    bare = api.client.post("/api/v1/subjects", content=body, headers=api.as_("staff"))
    assert bare.status_code == 422
    assert "(this one came without a Content-Type)" in bare.json()["message"]
    sent_right = api.client.post("/api/v1/subjects", json={"code": "S01"}, headers=api.as_("staff"))
    assert sent_right.status_code == 201


def test_a_json_sign_in_is_told_to_send_a_form(api: Api) -> None:
    sent = api.client.post(
        "/api/v1/auth/token", json={"username": "admin@lab.test", "password": "x"}
    )
    assert sent.status_code == 422
    assert sent.json()["message"].startswith("this route takes a form body")
    assert "Field required" not in sent.text


def test_pattern_failures_are_described_not_shown_as_regex(api: Api) -> None:
    code = api.client.post(
        "/api/v1/subjects", json={"code": "Jane Doe"}, headers=api.as_("staff")
    ).json()
    assert code["detail"][0]["field"] == "code"
    assert code["detail"][0]["msg"].startswith("'Jane Doe' is not a subject code: 1 to 64")
    assert "^[" not in code["message"]
    email = api.client.post(
        "/api/v1/users",
        json={"email": "jane", "password": "p" * 12},
        headers=api.as_("admin"),
    ).json()
    assert email["detail"][0]["msg"] == "'jane' is not an e-mail address like name@lab.org"
    schema = api.client.get("/openapi.json").json()["components"]["schemas"]
    assert schema["SubjectCreate"]["properties"]["code"]["pattern"].startswith("^[A-Za-z0-9]")


def _orange_pixels(png: bytes) -> int:
    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    r, g, b = pixels[..., 0], pixels[..., 1], pixels[..., 2]
    return int(((r > 230) & (g > 110) & (g < 150) & (b < 40)).sum())


def test_the_curve_png_draws_pi_hf_dashed_when_the_job_has_it() -> None:
    curve = [[0, 0.0], [1000, 0.4], [2000, 0.6]]
    assert _orange_pixels(curve_png(curve, "x")) == 0
    assert _orange_pixels(curve_png(curve, "x", hf_policy_spl=0.3)) > 100
