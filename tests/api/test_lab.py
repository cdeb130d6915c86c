"""Rigs, subjects and sessions: CRUD and the scheduling rules, on SQLite and PostgreSQL."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime, timedelta

from tests.api.conftest import Api


def _subject(api: Api, code: str) -> int:
    response = api.client.post("/api/v1/subjects", json={"code": code}, headers=api.as_("staff"))
    assert response.status_code == 201, response.text
    return response.json()["id"]


def _rig(api: Api, name: str) -> int:
    response = api.client.post("/api/v1/rigs", json={"name": name}, headers=api.as_("admin"))
    assert response.status_code == 201, response.text
    return response.json()["id"]


def _schedule(api: Api, **body: object):
    return api.client.post("/api/v1/sessions", json=body, headers=api.as_("staff"))


def test_racing_requests_for_one_slot_schedule_one_session(api_any_db: Api) -> None:
    """Scripts (or a double click) sending the same slot at once: the overlap check and the
    insert happen under a lock per subject and rig, so exactly one is scheduled and every
    other gets the 409 naming it, on SQLite and PostgreSQL (a reschedule takes the same
    lock)."""
    api = api_any_db
    subject, other_subject = _subject(api, "S01"), _subject(api, "S02")
    rig = _rig(api, "Room 1")
    slot = {"kind": "test", "scheduled_at": "2037-12-07T09:00:00Z", "duration_minutes": 60}
    bodies = [
        {**slot, "subject_id": subject},  # the same subject ...
        {**slot, "subject_id": other_subject, "rig_id": rig},  # ... or the same rig
    ]
    for body in bodies:
        with ThreadPoolExecutor(max_workers=8) as pool:
            answers = list(pool.map(lambda b: _schedule(api, **b), [body] * 8))
        statuses = sorted(answer.status_code for answer in answers)
        assert statuses == [201] + [409] * 7, [a.text for a in answers]
    listed = api.client.get("/api/v1/sessions", headers=api.as_("staff")).json()
    assert listed["total"] == 2


def test_subject_crud(api_any_db: Api) -> None:
    api = api_any_db
    staff = api.as_("staff")
    created = api.client.post(
        "/api/v1/subjects", json={"code": "S01", "notes": "right-handed"}, headers=staff
    )
    assert created.status_code == 201
    subject = created.json()
    assert (subject["code"], subject["notes"]) == ("S01", "right-handed")
    duplicate = api.client.post("/api/v1/subjects", json={"code": "S01"}, headers=staff)
    assert duplicate.status_code == 409
    assert duplicate.json() == {"detail": "subject code 'S01' is taken", "field": "code"}
    bad = api.client.post("/api/v1/subjects", json={"code": "Jane Doe"}, headers=staff)
    assert bad.status_code == 422
    assert bad.json()["detail"][0]["field"] == "code"
    _subject(api, "S02")
    listed = api.client.get("/api/v1/subjects?code=S0&limit=1", headers=api.as_("viewer")).json()
    assert (listed["total"], listed["limit"], [s["code"] for s in listed["items"]]) == (
        2,
        1,
        ["S01"],
    )
    updated = api.client.patch(
        f"/api/v1/subjects/{subject['id']}", json={"notes": "left"}, headers=staff
    )
    assert updated.json()["notes"] == "left"
    clash = api.client.patch(
        f"/api/v1/subjects/{subject['id']}", json={"code": "S02"}, headers=staff
    )
    assert clash.status_code == 409
    viewer = api.client.post("/api/v1/subjects", json={"code": "S03"}, headers=api.as_("viewer"))
    assert viewer.status_code == 403
    deleted = api.client.delete(f"/api/v1/subjects/{subject['id']}", headers=staff)
    assert deleted.status_code == 204
    missing = api.client.get(f"/api/v1/subjects/{subject['id']}", headers=staff)
    assert missing.status_code == 404
    assert missing.json() == {
        "detail": f"no subject with id {subject['id']}",
        "field": "subject_id",
    }


def test_sessions_refuse_overlaps_of_subject_or_rig(api_any_db: Api) -> None:
    api = api_any_db
    s1, s2 = _subject(api, "S01"), _subject(api, "S02")
    rig = _rig(api, "Room 1 BioSemi")
    first = _schedule(
        api,
        subject_id=s1,
        kind="calibration",
        rig_id=rig,
        scheduled_at="2037-12-07T10:00:00+01:00",
        duration_minutes=60,
    )
    assert first.status_code == 201, first.text
    first_id = first.json()["id"]
    assert first.json()["ends_at"] == "2037-12-07T10:00:00Z"
    assert first.json()["operator_id"] == api.user_ids["staff"]
    # same subject, other rig, overlapping by 30 minutes
    subject_clash = _schedule(api, subject_id=s1, kind="test", scheduled_at="2037-12-07T09:30:00Z")
    assert subject_clash.status_code == 409
    assert subject_clash.json() == {
        "detail": f"overlaps session {first_id} of the same subject "
        "(2037-12-07T09:00:00+00:00 to 2037-12-07T10:00:00+00:00)",
        "field": "scheduled_at",
    }
    # same rig, other subject
    rig_clash = _schedule(
        api,
        subject_id=s2,
        kind="rl",
        rig_id=rig,
        scheduled_at="2037-12-07T08:30:00Z",
        duration_minutes=45,
    )
    assert rig_clash.status_code == 409
    assert rig_clash.json()["detail"].startswith(f"overlaps session {first_id} of the same rig")
    # back to back is fine
    after = _schedule(
        api, subject_id=s2, kind="rl", rig_id=rig, scheduled_at="2037-12-07T10:00:00Z"
    )
    assert after.status_code == 201
    naive = _schedule(api, subject_id=s2, kind="rl", scheduled_at="2037-12-08T10:00:00")
    assert naive.status_code == 422
    assert naive.json()["detail"][0]["field"] == "scheduled_at"
    unknown = _schedule(api, subject_id=999, kind="rl", scheduled_at="2037-12-08T10:00:00Z")
    assert unknown.status_code == 422
    assert unknown.json() == {"detail": "no subject with id 999", "field": "subject_id"}
    # rescheduling into the other session's slot is refused; cancelling frees the slot
    moved = api.client.patch(
        f"/api/v1/sessions/{after.json()['id']}",
        json={"scheduled_at": "2037-12-07T09:15:00Z"},
        headers=api.as_("staff"),
    )
    assert moved.status_code == 409
    cancelled = api.client.post(f"/api/v1/sessions/{first_id}/cancel", headers=api.as_("staff"))
    assert cancelled.json()["status"] == "cancelled"
    moved = api.client.patch(
        f"/api/v1/sessions/{after.json()['id']}",
        json={"scheduled_at": "2037-12-07T09:15:00Z", "duration_minutes": 30},
        headers=api.as_("staff"),
    )
    assert moved.status_code == 200
    assert moved.json()["ends_at"] == "2037-12-07T09:45:00Z"
    again = api.client.post(f"/api/v1/sessions/{first_id}/cancel", headers=api.as_("staff"))
    assert again.status_code == 409


def test_a_start_in_the_past_needs_allow_past(api: Api) -> None:
    """A session dated in the past is refused at its start, naming the way to confirm it; a
    start a minute ago is not "past" (the form was filled in a moment ago); a reschedule
    into the past needs the same confirmation, other edits of a past session do not."""
    subject = _subject(api, "S01")
    staff = api.as_("staff")
    refused = _schedule(api, subject_id=subject, kind="rl", scheduled_at="2020-01-01T09:00:00Z")
    assert refused.status_code == 422
    assert refused.json() == {
        "detail": "starts in the past (2020-01-01 09:00 UTC); send allow_past: true to "
        "schedule it anyway (a session that has happened)",
        "field": "scheduled_at",
    }
    assert api.client.get("/api/v1/sessions", headers=staff).json()["total"] == 0
    happened = _schedule(
        api, subject_id=subject, kind="rl", scheduled_at="2020-01-01T09:00:00Z", allow_past=True
    )
    assert happened.status_code == 201, happened.text
    just_now = (datetime.now(UTC) - timedelta(minutes=1)).isoformat()
    assert _schedule(api, subject_id=subject, kind="test", scheduled_at=just_now).status_code == 201

    url = f"/api/v1/sessions/{happened.json()['id']}"
    assert api.client.patch(url, json={"notes": "late entry"}, headers=staff).status_code == 200
    same = {"scheduled_at": "2020-01-01T09:00:00Z", "duration_minutes": 90}
    assert api.client.patch(url, json=same, headers=staff).status_code == 200  # start unchanged
    earlier = {"scheduled_at": "2019-12-31T09:00:00Z"}
    moved = api.client.patch(url, json=earlier, headers=staff)
    assert (moved.status_code, moved.json()["field"]) == (422, "scheduled_at")
    moved = api.client.patch(url, json={**earlier, "allow_past": True}, headers=staff)
    assert moved.json()["scheduled_at"] == "2019-12-31T09:00:00Z"


def test_session_status_moves_forward_only(api: Api) -> None:
    subject = _subject(api, "S01")
    session = _schedule(
        api, subject_id=subject, kind="online", scheduled_at="2037-12-07T10:00:00Z"
    ).json()
    url = f"/api/v1/sessions/{session['id']}"
    staff = api.as_("staff")
    assert api.client.patch(url, json={"status": "completed"}, headers=staff).status_code == 409
    assert (
        api.client.patch(url, json={"status": "running"}, headers=staff).json()["status"]
        == "running"
    )
    late = api.client.patch(url, json={"scheduled_at": "2037-12-07T11:00:00Z"}, headers=staff)
    assert late.status_code == 409
    assert late.json()["field"] == "scheduled_at"
    assert (
        api.client.patch(url, json={"status": "completed"}, headers=staff).json()["status"]
        == "completed"
    )
    assert api.client.post(f"{url}/cancel", headers=staff).status_code == 409


def test_sessions_list_by_day_week_subject_status(api_any_db: Api) -> None:
    api = api_any_db
    s1, s2 = _subject(api, "S01"), _subject(api, "S02")
    for subject, start in (
        (s1, "2037-12-07T08:00:00Z"),
        (s2, "2037-12-07T23:30:00Z"),
        (s1, "2037-12-09T12:00:00Z"),
        (s2, "2037-12-14T12:00:00Z"),
    ):
        assert _schedule(api, subject_id=subject, kind="rl", scheduled_at=start).status_code == 201
    viewer = api.as_("viewer")

    def starts(query: str) -> list[str]:
        response = api.client.get(f"/api/v1/sessions?{query}", headers=viewer)
        assert response.status_code == 200, response.text
        return [s["scheduled_at"] for s in response.json()["items"]]

    assert starts("day=2037-12-07") == ["2037-12-07T08:00:00Z", "2037-12-07T23:30:00Z"]
    # in Berlin (UTC+1) the 23:30 UTC session is on the 8th
    assert starts("day=2037-12-08&tz=Europe/Berlin") == ["2037-12-07T23:30:00Z"]
    assert starts("week=2037-W50") == [
        "2037-12-07T08:00:00Z",
        "2037-12-07T23:30:00Z",
        "2037-12-09T12:00:00Z",
    ]
    assert starts(f"subject_id={s2}") == ["2037-12-07T23:30:00Z", "2037-12-14T12:00:00Z"]
    assert starts("status=cancelled") == []
    bad_tz = api.client.get("/api/v1/sessions?day=2037-12-07&tz=Mars/Olympus", headers=viewer)
    assert bad_tz.status_code == 422
    assert bad_tz.json() == {"detail": "unknown time zone 'Mars/Olympus'", "field": "tz"}
    bad_week = api.client.get("/api/v1/sessions?week=2026-W60", headers=viewer)
    assert bad_week.status_code == 422
    assert bad_week.json()["field"] == "week"
    too_many = api.client.get("/api/v1/sessions?limit=501", headers=viewer)
    assert too_many.status_code == 422
    assert too_many.json()["detail"][0]["field"] == "limit"


def test_rigs_are_managed_by_admins(api: Api) -> None:
    rig = _rig(api, "Room 2")
    duplicate = api.client.post("/api/v1/rigs", json={"name": "Room 2"}, headers=api.as_("admin"))
    assert duplicate.status_code == 409
    assert duplicate.json() == {"detail": "a rig named 'Room 2' exists", "field": "name"}
    subject = _subject(api, "S01")
    session = _schedule(
        api, subject_id=subject, kind="rl", rig_id=rig, scheduled_at="2037-12-07T10:00:00Z"
    )
    in_use = api.client.delete(f"/api/v1/rigs/{rig}", headers=api.as_("admin"))
    assert in_use.status_code == 409
    assert in_use.json()["detail"] == (
        f"rig {rig} is used by session {session.json()['id']}; set active=false instead"
    )
    off = api.client.patch(f"/api/v1/rigs/{rig}", json={"active": False}, headers=api.as_("admin"))
    assert off.json()["active"] is False
    inactive = _schedule(
        api, subject_id=subject, kind="rl", rig_id=rig, scheduled_at="2037-12-08T10:00:00Z"
    )
    assert inactive.status_code == 422
    assert inactive.json() == {"detail": "rig Room 2 is not active", "field": "rig_id"}
