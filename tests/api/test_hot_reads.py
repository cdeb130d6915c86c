"""The job list's hot path (``services.api.hot``) answers exactly as the route does: for
every request, with and without it, the same status, body and headers; it takes the plain
requests and leaves every other one to the route."""

from __future__ import annotations

import uuid
from typing import Any

import httpx
from sqlalchemy import insert

from services.api.hot import HotReads
from services.core.db.models import Job
from tests.api.conftest import Api


def _answers(api: Api, requests: list[tuple[str, dict[str, str]]]) -> list[tuple[Any, ...]]:
    def answer(response: httpx.Response) -> tuple[Any, ...]:
        headers = {k: v for k, v in response.headers.items() if k != "x-request-id"}
        return response.status_code, response.content, headers

    return [answer(api.client.get(url, headers=headers)) for url, headers in requests]


def _spy_on_hot_path(api: Api) -> list[bool]:
    """Whether the hot handler answered each request (True) or left it to the route."""
    app: Any = api.client.app
    entry = next(m for m in app.user_middleware if m.cls is HotReads)
    hot = entry.kwargs["routes"]["/api/v1/jobs"]
    answered: list[bool] = []

    async def spy(request: Any) -> Any:
        response = await hot(request)
        answered.append(response is not None)
        return response

    entry.kwargs["routes"] = {"/api/v1/jobs": spy}
    app.middleware_stack = None  # rebuilt at the next request
    return answered


def _without_hot_path(api: Api) -> None:
    app: Any = api.client.app
    app.user_middleware = [m for m in app.user_middleware if m.cls is not HotReads]
    app.middleware_stack = None


def test_hot_job_list_answers_as_the_route(api_any_db: Api) -> None:
    api = api_any_db
    client = api.client
    parent = uuid.uuid4().hex
    rows = [
        {
            "id": parent if i == 0 else uuid.uuid4().hex,
            "kind": "reproduce" if i == 0 else "reproduce_run" if i < 4 else "guided_ppo",
            "parent_id": parent if 0 < i < 4 else None,
            "config": {"seed": i},
            "status": ("queued", "running", "succeeded")[i % 3],
            "submitter_id": api.user_ids["staff"] if i % 2 else None,
        }
        for i in range(9)
    ]
    with client.app.state.engine.begin() as connection:  # type: ignore[attr-defined]
        connection.execute(insert(Job), rows)
    created = client.post("/api/v1/tokens", json={"name": "s"}, headers=api.as_("staff")).json()
    api_token = {"Authorization": f"Bearer {created['token']}"}
    revoked = client.post("/api/v1/tokens", json={"name": "r"}, headers=api.as_("staff")).json()
    assert client.delete(f"/api/v1/tokens/{revoked['id']}", headers=api.as_("staff")).is_success
    viewer_token = api.as_("viewer")["Authorization"].removeprefix("Bearer ")
    plain = [
        "",
        "?limit=50",
        "?limit=3&offset=2",
        "?offset=0&limit=500",
        "?offset=100",
        "?status=queued",
        f"?kind=reproduce_run&parent_id={parent}",
        f"?submitter_id={api.user_ids['staff']}&status=running",
        "?limit=%35",  # percent-encoded 5
    ]
    odd = [
        "?limit=0",
        "?limit=501",
        "?limit=+5",
        "?limit=05",
        "?limit=%205",
        "?limit=5.0",
        "?limit=5&limit=6",
        "?limit=",
        "?offset=-1",
        "?offset=1000000001",
        "?status=nope",
        "?kind=Reproduce",
        "?parent_id=",
        "?parent_id=" + "x" * 33,
        "?submitter_id=0",
        "?submitter_id=99999999999999999999999",
        "?unknown=1",
        "?limit=%EF%BC%95",  # a full-width 5: a digit, but not ASCII
    ]
    signed_in = [api.as_("viewer"), api_token]
    refused = [
        {},
        {"Authorization": f"Basic {viewer_token}"},
        {"Authorization": "Bearer "},
        {"Authorization": f"bearer {viewer_token}"},  # the scheme is case-insensitive
        {"Authorization": f"Bearer {revoked['token']}"},
        {"Authorization": "Bearer not-a-token"},
    ]
    requests = [(f"/api/v1/jobs{q}", h) for q in plain + odd for h in signed_in + refused]
    answered = _spy_on_hot_path(api)
    hot = _answers(api, requests)
    _without_hot_path(api)
    assert _answers(api, requests) == hot
    assert len(answered) == len(requests)
    by_request = dict(zip((f"{u} {h}" for u, h in requests), answered, strict=True))
    for query in plain:  # the plain reads are the hot path's, the rest the route's
        for headers in [*signed_in, refused[3]]:
            assert by_request[f"/api/v1/jobs{query} {headers}"], (query, headers)
    assert sum(answered) == len(plain) * 3
    assert {status for status, _, _ in hot} == {200, 401, 422}
    assert client.app.state.engine.pool.checkedout() == 0  # type: ignore[attr-defined]
