"""The api used from outside, carelessly or maliciously: NUL characters, timestamps at the
ends of the calendar, impossible token subjects and ids, repeated list entries, bodies that
are not JSON, and deletes of what a running job still uses. Each must be a clear 4xx naming
the field (never a 5xx, never silently accepted) and must lose nothing already stored."""

from __future__ import annotations

from datetime import timedelta
from typing import Any

import jwt
import pytest
from sqlalchemy import update

from services.api.security import JWT_ALGORITHM
from services.core.db.base import utcnow
from services.core.db.models import Recording
from tests.api.conftest import Api

NUL = "\x00"


def _subject(api: Api, code: str) -> int:
    created = api.client.post("/api/v1/subjects", json={"code": code}, headers=api.as_("staff"))
    assert created.status_code == 201, created.text
    return created.json()["id"]


def _session(api: Api, subject_id: int, kind: str = "calibration", day: int = 1) -> int:
    created = api.client.post(
        "/api/v1/sessions",
        json={"subject_id": subject_id, "kind": kind, "scheduled_at": f"2030-01-{day:02d}T09:00Z"},
        headers=api.as_("staff"),
    )
    assert created.status_code == 201, created.text
    return created.json()["id"]


def _field(response: Any) -> str | None:
    body = response.json()
    detail = body["detail"]
    return detail[0]["field"] if isinstance(detail, list) else body["field"]


def test_text_with_a_nul_character_is_refused_naming_the_field(api_any_db: Api) -> None:
    """PostgreSQL cannot store or even compare NUL: every such input was a 500 there (and
    stored as is on SQLite)."""
    api = api_any_db
    client, staff, admin = api.client, api.as_("staff"), api.as_("admin")
    subject_id = _subject(api, "S01")
    session_id = _session(api, subject_id)
    refused_bodies = [
        ("POST", "/api/v1/subjects", {"code": "S02", "notes": f"a{NUL}b"}, staff, "notes"),
        ("PATCH", f"/api/v1/subjects/{subject_id}", {"notes": NUL}, staff, "notes"),
        ("POST", "/api/v1/rigs", {"name": f"rig{NUL}"}, admin, "name"),
        ("POST", "/api/v1/tokens", {"name": f"ci{NUL}"}, staff, "name"),
        ("POST", "/api/v1/users", {"email": f"a{NUL}@lab.test", "password": "p" * 12}, admin,
         "email"),
        ("POST", "/api/v1/sessions", {"subject_id": subject_id, "kind": "rl",
         "scheduled_at": "2031-01-01T00:00Z", "notes": NUL}, staff, "notes"),
        ("PATCH", f"/api/v1/sessions/{session_id}", {"notes": NUL}, staff, "notes"),
        ("POST", f"/api/v1/sessions/{session_id}/start",
         {"eeg_source": "lsl", "stream_name": f"EEG{NUL}"}, staff, "stream_name"),
    ]  # fmt: skip
    for method, url, body, headers, field in refused_bodies:
        response = client.request(method, url, json=body, headers=headers)
        assert response.status_code == 422, (method, url, response.text)
        assert _field(response) == field, response.text
    refused_queries = [
        ("/api/v1/subjects", {"code": NUL}, "code"),
        ("/api/v1/jobs", {"parent_id": f"ab{NUL}"}, "parent_id"),  # the hot list route
        ("/api/v1/artifacts", {"kind": NUL}, "kind"),
        ("/api/v1/audit", {"action": NUL}, "action"),
    ]
    for url, params, field in refused_queries:
        response = client.get(url, params=params, headers=admin)
        assert response.status_code == 422, (url, response.text)
        assert _field(response) == field
    for url in ("/api/v1/jobs/ab%00cd", "/api/v1/artifacts/ab%00cd", "/api/v1/jobs/%00/curve"):
        response = client.get(url, headers=admin)
        assert response.status_code == 404, (url, response.text)
    login = client.post("/api/v1/auth/token", data={"username": f"a{NUL}@b", "password": "x"})
    assert login.status_code == 401
    upload = client.post(
        f"/api/v1/sessions/{session_id}/recordings",
        params={"filename": f"s01{NUL}.bdf"},
        content=b"not empty",
        headers={**staff, "content-type": "application/octet-stream"},
    )
    assert upload.status_code == 422, upload.text
    assert upload.json()["field"] == "filename"
    # nothing was stored or changed
    subjects = client.get("/api/v1/subjects", headers=staff).json()
    assert [(s["code"], s["notes"]) for s in subjects["items"]] == [("S01", "")]
    assert client.get(f"/api/v1/sessions/{session_id}", headers=staff).json()["notes"] == ""
    assert client.get("/api/v1/recordings", headers=staff).json()["total"] == 0


@pytest.mark.parametrize(
    "scheduled_at", ["9999-12-31T23:30:00+00:00", "0001-01-01T00:00:00+05:00", "1899-12-31T23:00Z"]
)
def test_a_session_at_the_ends_of_the_calendar_is_422(api: Api, scheduled_at: str) -> None:
    """Its end (start + duration) or its UTC time overflowed: a 500."""
    subject_id = _subject(api, "S01")
    session_id = _session(api, subject_id)
    staff = api.as_("staff")
    body = {"subject_id": subject_id, "kind": "rl", "scheduled_at": scheduled_at}
    created = api.client.post("/api/v1/sessions", json=body, headers=staff)
    assert created.status_code == 422, created.text
    assert _field(created) == "scheduled_at"
    assert "between 1900-01-01 and 9000-01-01" in created.json()["message"]
    moved = api.client.patch(
        f"/api/v1/sessions/{session_id}", json={"scheduled_at": scheduled_at}, headers=staff
    )
    assert moved.status_code == 422, moved.text
    kept = api.client.get(f"/api/v1/sessions/{session_id}", headers=staff).json()
    assert kept["scheduled_at"] == "2030-01-01T09:00:00Z"


@pytest.mark.parametrize(
    ("params", "field"),
    [
        ({"day": "9999-12-31", "tz": "Pacific/Kiritimati"}, "day"),
        ({"day": "0001-01-01", "tz": "Asia/Tokyo"}, "day"),
        ({"week": "9999-W52"}, "week"),
    ],
)
def test_listing_sessions_at_the_ends_of_the_calendar_is_422(
    api: Api, params: dict[str, str], field: str
) -> None:
    response = api.client.get("/api/v1/sessions", params=params, headers=api.as_("viewer"))
    assert response.status_code == 422, response.text
    assert response.json()["field"] == field
    assert "out of the calendar's range" in response.json()["detail"]


def test_frame_shown_at_the_ends_of_the_calendar_is_422(api: Api) -> None:
    session_id = _session(api, _subject(api, "S01"))
    started = api.client.post(
        f"/api/v1/sessions/{session_id}/start", json={"accelerated": True}, headers=api.as_("staff")
    )
    assert started.status_code == 201, started.text
    url = f"/api/v1/sessions/{session_id}/frames-shown"
    for shown_at in ("0001-01-01T00:00:00+05:00", "9999-12-31T23:59:59-05:00"):
        response = api.client.post(
            url, json={"step": 1, "shown_at": shown_at}, headers=api.as_("viewer")
        )
        assert response.status_code == 422, response.text
        assert _field(response) == "shown_at"


def test_an_access_token_naming_an_impossible_user_is_401(api: Api) -> None:
    """A validly signed token whose subject no integer column can hold: a 500 before."""
    key = api.client.app.state.jwt_key  # type: ignore[attr-defined]
    for subject in ("99999999999999999999", str(2**31), "\u0661"):  # the last: Arabic-Indic 1
        token = jwt.encode(
            {"sub": subject, "exp": utcnow() + timedelta(minutes=5), "typ": "access"},
            key,
            algorithm=JWT_ALGORITHM,
        )
        headers = {"Authorization": f"Bearer {token}"}
        for url in ("/api/v1/users/me", "/api/v1/jobs"):
            response = api.client.get(url, headers=headers)
            assert response.status_code == 401, (subject, url, response.text)
            assert response.json()["field"] == "token"


def test_live_start_with_a_classifier_id_beyond_any_row_is_422(api: Api) -> None:
    session_id = _session(api, _subject(api, "S01"), kind="online")
    for classifier_id in (2**31, 10**20):
        response = api.client.post(
            f"/api/v1/sessions/{session_id}/start",
            json={"classifier_id": classifier_id},
            headers=api.as_("staff"),
        )
        assert response.status_code == 422, response.text
        assert response.json()["field"] == "classifier_id"
    live = api.client.get(f"/api/v1/sessions/{session_id}/live", headers=api.as_("viewer"))
    assert live.status_code == 404  # never started


@pytest.mark.parametrize(
    ("config", "field"),
    [
        ({"tasks": ["sssg", "SSSG"]}, "config.tasks"),
        ({"methods": ["rl_sparse", "rl_sparse"]}, "config.methods"),
        ({"accuracies": [0.6, 0.7, 0.6]}, "config.accuracies"),
        ({"treatments": ["authors", "authors"]}, "config.treatments"),
    ],
)
def test_a_reproduce_job_with_a_repeated_entry_is_422(
    api: Api, config: dict[str, Any], field: str
) -> None:
    """A repeated task, method, accuracy or treatment queued the same runs twice (and
    counted them twice in the results)."""
    response = api.client.post(
        "/api/v1/jobs",
        json={"kind": "reproduce", "config": {"quick": True, **config}},
        headers=api.as_("staff"),
    )
    assert response.status_code == 422, response.text
    assert _field(response) == field
    assert "repeated" in response.json()["message"]
    assert api.client.get("/api/v1/jobs", headers=api.as_("staff")).json()["total"] == 0


def test_job_list_with_an_unknown_kind_names_the_field_kind(api: Api) -> None:
    response = api.client.get("/api/v1/jobs", params={"kind": "bogus"}, headers=api.as_("viewer"))
    assert response.status_code == 422
    assert [e["field"] for e in response.json()["detail"]] == ["kind"]
    assert "'reproduce_run'" in response.json()["message"]
    runs = api.client.get("/api/v1/jobs?kind=reproduce_run", headers=api.as_("viewer"))
    assert runs.status_code == 200


@pytest.mark.parametrize("body", [b"{bad", b'{"code": "S1",}', b"\n\n  nope"])
def test_a_body_that_is_not_json_names_the_body(api: Api, body: bytes) -> None:
    response = api.client.post(
        "/api/v1/subjects",
        content=body,
        headers={**api.as_("staff"), "content-type": "application/json"},
    )
    assert response.status_code == 422
    [entry] = response.json()["detail"]
    assert entry["field"] == "body"
    assert response.json()["message"].startswith("body: the body is not valid JSON: ")
    assert "at character" in response.json()["message"]


def test_a_subject_a_live_session_runs_on_is_not_deleted(api: Api) -> None:
    """Deleting the subject (staff, no purge) silently deleted its running session, its
    live run and the live job's data; now 409 while the job is active, and live data
    needs an admin's purge like recordings do."""
    subject_id = _subject(api, "S01")
    session_id = _session(api, subject_id)
    staff, admin = api.as_("staff"), api.as_("admin")
    run = api.client.post(
        f"/api/v1/sessions/{session_id}/start", json={"accelerated": True}, headers=staff
    )
    assert run.status_code == 201, run.text
    job_id = run.json()["job_id"]
    url = f"/api/v1/subjects/{subject_id}"
    for headers, query in ((staff, ""), (admin, "?purge=true")):
        busy = api.client.delete(url + query, headers=headers)
        assert busy.status_code == 409, busy.text
        assert busy.json()["field"] == "subject_id"
        assert f"live_session job {job_id} (queued)" in busy.json()["detail"]
    assert api.client.get(f"/api/v1/sessions/{session_id}", headers=staff).status_code == 200
    assert api.client.post(f"/api/v1/jobs/{job_id}/cancel", headers=staff).status_code == 200
    kept = api.client.delete(url, headers=staff)
    assert kept.status_code == 409
    assert kept.json()["field"] == "purge"
    assert "1 live run(s)" in kept.json()["detail"]
    live = api.client.get(f"/api/v1/sessions/{session_id}/live", headers=staff)
    assert live.status_code == 200
    purged = api.client.delete(url + "?purge=true", headers=admin)
    assert purged.status_code == 204
    assert api.client.get(f"/api/v1/sessions/{session_id}", headers=staff).status_code == 404


def test_a_recording_a_calibration_job_uses_is_not_deleted(api: Api) -> None:
    session_id = _session(api, _subject(api, "S01"))
    staff, admin = api.as_("staff"), api.as_("admin")
    upload = api.client.post(
        f"/api/v1/sessions/{session_id}/recordings",
        params={"filename": "s01.bdf"},
        content=b"a recording",
        headers={**staff, "content-type": "application/octet-stream"},
    )
    assert upload.status_code == 201, upload.text
    recording_id = upload.json()["id"]
    with api.client.app.state.sessions() as db:  # type: ignore[attr-defined]
        db.execute(
            update(Recording).where(Recording.id == recording_id).values(validation_status="valid")
        )
        db.commit()
    job = api.client.post(
        "/api/v1/jobs",
        json={"kind": "eeg_calibration", "config": {"recording_id": recording_id}},
        headers=staff,
    )
    assert job.status_code == 201, job.text
    url = f"/api/v1/recordings/{recording_id}"
    refused = api.client.delete(url, headers=admin)
    assert refused.status_code == 409, refused.text
    assert refused.json()["field"] == "recording_id"
    assert job.json()["id"] in refused.json()["detail"]
    assert api.client.get(f"{url}/file", headers=staff).content == b"a recording"
    api.client.post(f"/api/v1/jobs/{job.json()['id']}/cancel", headers=staff)
    assert api.client.delete(url, headers=admin).status_code == 204


def test_job_lifecycle_refusals_are_409_or_404(api: Api) -> None:
    """Already right: cancel twice, retry a queued job, the model of a job without one."""
    staff = api.as_("staff")
    job = api.client.post(
        "/api/v1/jobs",
        json={"kind": "guided_ppo", "config": {"task": "sssg", "method": "rl_sparse"}},
        headers=staff,
    ).json()
    url = f"/api/v1/jobs/{job['id']}"
    assert api.client.post(f"{url}/retry", headers=staff).status_code == 409
    assert api.client.post(f"{url}/cancel", headers=staff).json()["status"] == "cancelled"
    again = api.client.post(f"{url}/cancel", headers=staff)
    assert again.status_code == 409
    assert again.json() == {"detail": f"job {job['id']} is already cancelled", "field": "job_id"}
    model = api.client.get(f"{url}/model", headers=staff)
    assert model.status_code == 404
    assert "has no model yet" in model.json()["detail"]
    assert api.client.post(f"{url}/cancel", headers=api.as_("viewer")).status_code == 403


def test_a_deactivated_users_api_token_stops_at_once(api: Api) -> None:
    """Already right: deactivation stops the user's API tokens and access tokens."""
    viewer = api.as_("viewer")
    token = api.client.post("/api/v1/tokens", json={"name": "ci"}, headers=viewer).json()
    script = {"Authorization": f"Bearer {token['token']}"}
    assert api.client.get("/api/v1/users/me", headers=script).status_code == 200
    deactivate = api.client.patch(
        f"/api/v1/users/{api.user_ids['viewer']}", json={"active": False}, headers=api.as_("admin")
    )
    assert deactivate.status_code == 200
    for headers in (script, viewer):
        for url in ("/api/v1/users/me", "/api/v1/jobs"):
            assert api.client.get(url, headers=headers).status_code == 401
