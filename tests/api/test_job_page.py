"""The job list selects only ``JobPublic``'s columns: its JSON must be the document
``Page[JobPublic]`` gives for the same jobs loaded whole, on SQLite and PostgreSQL, whatever
the filters, the page, nulls, unicode, large numbers and timestamps; and its sign-in must
refuse what every other route refuses, at once."""

from __future__ import annotations

import json
import uuid
from datetime import UTC, datetime, timedelta, timezone
from typing import Any

import pytest
from sqlalchemy import insert, select, text

from services.api.schemas.common import Page
from services.api.schemas.jobs import JobPublic
from services.core.db.models import Job
from tests.api.conftest import Api

BASE = datetime(2026, 3, 1, 12, 0, 0, tzinfo=UTC)
UNICODE = 'é 日本語 🧠 "quoted" back\\slash tab\t newline\n nul-free \u2028 <tag> & %s {x}'


def _rows(api: Api) -> list[dict[str, Any]]:
    """Jobs covering what a page can hold: every nullable column null and set, unicode,
    large and awkward numbers, timestamps with and without microseconds, given in another
    zone, and a reproduce job with its runs (parent_id)."""
    submitters = [None, api.user_ids["staff"], api.user_ids["admin"]]
    rows = []
    parent = uuid.uuid4().hex
    for i in range(23):
        created = BASE + timedelta(minutes=i, microseconds=0 if i % 3 == 0 else 1000 * i + 7)
        finished = i % 4 != 0
        rows.append(
            {
                "id": parent if i == 0 else uuid.uuid4().hex,
                "kind": ("reproduce" if i == 0 else "reproduce_run" if i < 5 else "guided_ppo"),
                "parent_id": parent if 0 < i < 5 else None,
                "config": {
                    "task": "sssg",
                    "seed": i,
                    "note": UNICODE if i % 2 else "ascii",
                    "big": 2**63 + i,
                    "huge": 10**30,
                    "tiny": 5e-324,
                    "float": 0.1 + 0.2,
                    "neg": -1.5e300,
                    "nested": {"list": [1, 2.5, None, True, False, "ü"], "empty": {}},
                    "ppo": {},
                },
                "status": ("queued", "running", "succeeded", "failed", "cancelled")[i % 5],
                "progress": (0.0, 1.0, 0.1 + 0.2, 1 / 3, 1e-7)[i % 5],
                "attempts": i % 4,
                "max_attempts": 2**31 - 1 if i == 7 else 3,
                "resumed_from_step": None if i % 2 else 2048 * i,
                "steps_done": 2**31 - 1 if i == 9 else 100 * i,
                "curve": [[0, 0.0], [2048, 0.5]],
                "result": None if i % 3 else {"final_spl": 0.71, "text": UNICODE, "n": 2**53 + 1},
                "error": None if i % 5 != 3 else f"ValueError: {UNICODE}",
                "traceback": "Traceback (most recent call last): ..." if i % 5 == 3 else None,
                "submitter_id": submitters[i % 3],
                "cancel_requested": i % 5 == 4,
                "created_at": created,
                "updated_at": created.astimezone(timezone(timedelta(hours=5, minutes=30))),
                "started_at": None if i % 5 == 0 else created + timedelta(seconds=1),
                "finished_at": created + timedelta(hours=1, microseconds=999_999)
                if finished
                else None,
            }
        )
    return rows


def _reference(api: Api, filters: dict[str, Any], limit: int, offset: int) -> dict[str, Any]:
    """The page as ``Page[JobPublic]`` gives it, from ORM objects filtered and ordered here."""
    with api.client.app.state.sessions() as db:
        jobs = db.scalars(select(Job)).all()
        matching = [j for j in jobs if all(getattr(j, k) == v for k, v in filters.items())]
        matching.sort(key=lambda j: j.id)
        matching.sort(key=lambda j: j.created_at, reverse=True)
        page = Page[JobPublic].model_validate(
            {
                "items": matching[offset : offset + limit],
                "total": len(matching),
                "limit": limit,
                "offset": offset,
            }
        )
        return json.loads(page.model_dump_json())


QUERIES = [
    ({}, 50, 0),
    ({}, 5, 0),
    ({}, 5, 20),
    ({}, 1, 22),
    ({}, 10, 23),  # past the end: no rows, the total still counted
    ({}, 10, 1000),
    ({"status": "failed"}, 50, 0),
    ({"status": "running"}, 2, 1),
    ({"kind": "reproduce_run"}, 50, 0),
    ({"kind": "eeg_calibration"}, 50, 0),  # none
    ({"submitter_id": "staff"}, 50, 0),
    ({"parent_id": "parent"}, 3, 1),
    ({"status": "succeeded", "kind": "guided_ppo", "submitter_id": "admin"}, 50, 0),
]


def test_job_list_is_the_pydantic_page_of_its_rows(api_any_db: Api) -> None:
    api = api_any_db
    rows = _rows(api)
    with api.client.app.state.engine.begin() as connection:
        connection.execute(insert(Job), rows)
    parent = rows[0]["id"]
    for filters, limit, offset in QUERIES:
        filters = {
            k: api.user_ids[v] if k == "submitter_id" else parent if k == "parent_id" else v
            for k, v in filters.items()
        }
        response = api.client.get(
            "/api/v1/jobs",
            params={**filters, "limit": limit, "offset": offset},
            headers=api.as_("viewer"),
        )
        assert response.status_code == 200, response.text
        assert response.headers["content-type"] == "application/json"
        page = response.json()
        assert page == _reference(api, filters, limit, offset), (filters, limit, offset)
        for item in page["items"]:
            assert list(item) == [*JobPublic.model_fields, *JobPublic.model_computed_fields]
    whole = api.client.get("/api/v1/jobs?limit=50", headers=api.as_("viewer")).json()
    assert whole["total"] == len(rows) and len(whole["items"]) == len(rows)
    first = next(item for item in whole["items"] if item["id"] == rows[6]["id"])
    assert first["config"]["note"] == "ascii" and first["config"]["big"] == 2**63 + 6
    assert first["created_at"] == "2026-03-01T12:06:00Z"  # no fraction when it is zero
    assert first["updated_at"] == "2026-03-01T12:06:00Z"  # given at +05:30, written in UTC
    odd = next(item for item in whole["items"] if item["id"] == rows[7]["id"])
    assert odd["config"]["note"] == UNICODE and odd["max_attempts"] == 2**31 - 1
    assert odd["created_at"] == "2026-03-01T12:07:00.007007Z"
    assert odd["finished_at"] == "2026-03-01T13:07:01.007006Z"


def test_each_job_says_what_it_does_even_of_a_kind_or_config_it_does_not_know(
    api: Api,
) -> None:
    """``summary`` is the kind's one line; a row of another version's kind, or a config its
    kind's summary cannot read, still lists (the kind, or its title)."""
    base = _rows(api)[5]
    rows = [
        {**base, "id": "a" * 32, "kind": "guided_ppo",
         "config": {"task": "sssg", "method": "hf_sparse", "accuracy": 0.7, "seed": 3,
                    "total_steps": 40000}},
        {**base, "id": "b" * 32, "kind": "guided_ppo", "config": {"total_steps": "many"}},
        {**base, "id": "c" * 32, "kind": "from_the_future", "config": {}},
    ]  # fmt: skip
    with api.client.app.state.engine.begin() as connection:
        connection.execute(insert(Job), rows)
    response = api.client.get("/api/v1/jobs?limit=50", headers=api.as_("viewer"))
    assert response.status_code == 200, response.text
    summaries = {item["id"][0]: item["summary"] for item in response.json()["items"]}
    assert summaries == {
        "a": "SSSG hf_sparse C=0.7 seed 3, 40,000 steps",
        "b": "Guided-PPO run",
        "c": "from_the_future",
    }


def test_job_list_writes_non_finite_floats_as_pydantic_does(api: Api) -> None:
    """SQLite can store NaN and Infinity in a JSON column (PostgreSQL's json type cannot):
    the page gives null there, as pydantic does, and stays valid JSON."""
    row = {**_rows(api)[5], "result": {"spl": float("nan"), "max": float("inf"), "ok": 1}}
    with api.client.app.state.engine.begin() as connection:
        connection.execute(insert(Job), [row])
    response = api.client.get("/api/v1/jobs", headers=api.as_("viewer"))
    assert response.json() == _reference(api, {}, 50, 0)
    assert response.json()["items"][0]["result"] == {"spl": None, "max": None, "ok": 1}


def test_job_list_signs_in_like_every_route(api_any_db: Api) -> None:
    """API tokens: the list works with one, and stops at once when it is revoked or its
    account deactivated; an expired one is refused; a missing token is a 401 before any
    query-parameter check."""
    api = api_any_db
    client = api.client
    created = client.post(
        "/api/v1/tokens", json={"name": "script"}, headers=api.as_("viewer")
    ).json()
    token = {"Authorization": f"Bearer {created['token']}"}
    assert client.get("/api/v1/jobs", headers=token).json()["total"] == 0
    listed = client.get("/api/v1/tokens", headers=api.as_("viewer")).json()["items"]
    assert listed[0]["last_used_at"] is not None  # the use is recorded
    assert client.delete(f"/api/v1/tokens/{created['id']}", headers=api.as_("viewer")).is_success
    refused = client.get("/api/v1/jobs", headers=token)
    assert refused.status_code == 401
    assert refused.json() == {"detail": "unknown or revoked API token", "field": "token"}

    other = client.post("/api/v1/tokens", json={"name": "two"}, headers=api.as_("staff")).json()
    token = {"Authorization": f"Bearer {other['token']}"}
    assert client.get("/api/v1/jobs", headers=token).status_code == 200
    patched = client.patch(
        f"/api/v1/users/{api.user_ids['staff']}", json={"active": False}, headers=api.as_("admin")
    )
    assert patched.status_code == 200
    for headers in (token, api.as_("staff")):  # API token and access token alike
        refused = client.get("/api/v1/jobs", headers=headers)
        assert refused.status_code == 401
        assert refused.json() == {"detail": "account unknown or deactivated", "field": "token"}

    expiring = client.post(
        "/api/v1/tokens", json={"name": "three", "expires_in_days": 1}, headers=api.as_("admin")
    ).json()
    from services.core.db.models import ApiToken

    with client.app.state.sessions() as db:
        db.get(ApiToken, expiring["id"]).expires_at = BASE  # type: ignore[union-attr]
        db.commit()
    refused = client.get("/api/v1/jobs", headers={"Authorization": f"Bearer {expiring['token']}"})
    assert refused.status_code == 401
    assert refused.json() == {"detail": "API token expired", "field": "token"}

    missing = client.get("/api/v1/jobs?limit=0")
    assert missing.status_code == 401 and missing.headers["www-authenticate"] == "Bearer"
    for bad in ("bgrl_not-a-token", "not.a.jwt"):  # a bad token is told before a bad query
        refused = client.get(
            "/api/v1/jobs?limit=0&status=nope", headers={"Authorization": f"Bearer {bad}"}
        )
        assert refused.status_code == 401 and refused.json()["field"] == "token"
    bad_limit = client.get("/api/v1/jobs?limit=0", headers=api.as_("viewer"))
    assert bad_limit.status_code == 422 and bad_limit.json()["detail"][0]["field"] == "limit"
    assert client.app.state.engine.pool.checkedout() == 0  # type: ignore[attr-defined]


@pytest.mark.parametrize("role", ["viewer", "staff", "admin"])
def test_every_role_reads_the_job_list(api: Api, role: str) -> None:
    assert api.client.get("/api/v1/jobs", headers=api.as_(role)).status_code == 200


def test_job_list_reads_timestamps_stored_in_another_text_form(api: Api) -> None:
    """A SQLite row written by other means (a timestamp without its fraction) is not in
    the form the database formats: the page parses it, and still equals pydantic's."""
    rows = _rows(api)[:3]
    with api.client.app.state.engine.begin() as connection:
        connection.execute(insert(Job), rows)
        connection.execute(
            text("UPDATE jobs SET created_at = '2026-03-01 12:00:00', started_at = :odd"),
            {"odd": "2026-03-01 12:00:01"},
        )
    response = api.client.get("/api/v1/jobs", headers=api.as_("viewer"))
    assert response.json() == _reference(api, {}, 50, 0)
    assert response.json()["items"][0]["created_at"] == "2026-03-01T12:00:00Z"


def test_no_two_routes_share_a_method_and_path(api: Api) -> None:
    """The routers are included jobs first (the list is read most): that must change what a
    request costs, never which route answers it."""
    from fastapi.routing import APIWebSocketRoute, iter_route_contexts

    from services.api.app import ROUTERS
    from services.api.routes import jobs

    assert ROUTERS[0] is jobs.router
    seen: dict[tuple[str, str | None], str | None] = {}
    for route in iter_route_contexts(api.client.app.routes):  # included routers walked
        if isinstance(route.original_route, APIWebSocketRoute):
            methods = {"WEBSOCKET"}
        else:
            methods = set(getattr(route, "methods", None) or ())
        for method in methods:
            key = (method, route.path)
            assert key not in seen, f"{method} {route.path}: {seen[key]} and {route.name}"
            seen[key] = route.name
    assert ("GET", "/api/v1/jobs") in seen and ("WEBSOCKET", "/api/v1/jobs/{job_id}/events") in seen


def test_openapi_documents_the_job_page(api: Api) -> None:
    """The list answers its JSON bytes itself; its schema is still ``Page[JobPublic]``."""
    schema = api.client.get("/openapi.json").json()
    answer = schema["paths"]["/api/v1/jobs"]["get"]["responses"]["200"]
    ref = answer["content"]["application/json"]["schema"]["$ref"]
    page = schema["components"]["schemas"][ref.rsplit("/", 1)[1]]
    assert page["properties"]["items"]["items"]["$ref"].endswith("/JobPublic")
    assert set(page["required"]) == {"items", "total", "limit", "offset"}
