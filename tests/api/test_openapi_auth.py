"""Every protected route, found by walking the OpenAPI schema, refuses bad credentials."""

from __future__ import annotations

import json
from datetime import timedelta
from pathlib import Path

import jwt
import pytest
from fastapi.routing import APIRoute
from fastapi.testclient import TestClient

from services.api.app import ROUTERS
from services.api.deps import bearer_token, get_current_user, require_admin, require_staff
from services.api.security import JWT_ALGORITHM
from services.core.db.base import utcnow
from tests.api.conftest import Api

PUBLIC = {
    ("/healthz", "get"),
    ("/readyz", "get"),
    ("/health", "get"),
    ("/api/v1/auth/token", "post"),
}


def _dependency_calls(route: APIRoute) -> set[object]:
    calls: set[object] = set()
    stack = list(route.dependant.dependencies)
    while stack:
        dep = stack.pop()
        calls.add(dep.call)
        stack.extend(dep.dependencies)
    return calls


def _required_role(path: str, method: str) -> str | None:
    for router in ROUTERS:
        for route in router.routes:
            if not isinstance(route, APIRoute) or route.path != path:
                continue
            if method.upper() not in route.methods:
                continue
            calls = _dependency_calls(route)
            if require_admin in calls:
                return "admin"
            if require_staff in calls:
                return "staff"
            if get_current_user in calls or bearer_token in calls:  # any role
                return "viewer"
            return None
    raise AssertionError(f"{method} {path} is in the schema but not among the routes")


def _operations(client: TestClient) -> list[tuple[str, str, str]]:
    """(schema path, method, concrete URL) of every operation in /openapi.json."""
    schema = client.get("/openapi.json").json()
    operations = []
    for path, item in schema["paths"].items():
        for method, operation in item.items():
            url = path
            for param in operation.get("parameters", []):
                if param["in"] == "path":
                    is_int = param["schema"].get("type") == "integer"
                    url = url.replace("{" + param["name"] + "}", "1" if is_int else "a" * 32)
            operations.append((path, method, url))
    return operations


def _expired_token(api: Api) -> str:
    now = utcnow()
    claims = {
        "sub": str(api.user_ids["admin"]),
        "iat": now - timedelta(hours=2),
        "exp": now - timedelta(hours=1),
        "typ": "access",
    }
    return jwt.encode(claims, api.client.app.state.jwt_key, algorithm=JWT_ALGORITHM)


def test_every_route_but_health_and_login_requires_auth(api: Api) -> None:
    operations = _operations(api.client)
    assert len(operations) >= 40
    protected = [op for op in operations if (op[0], op[1]) not in PUBLIC]
    assert {(p, m) for p, m, _ in operations} - {(p, m) for p, m, _ in protected} == PUBLIC
    expired = _expired_token(api)
    forged = jwt.encode(
        {"sub": str(api.user_ids["admin"]), "exp": utcnow() + timedelta(hours=1), "typ": "access"},
        "not-the-key-" * 4,
        algorithm=JWT_ALGORITHM,
    )
    bad_headers = {
        "missing": {},
        "malformed": {"Authorization": "Bearer not-a-token"},
        "not bearer": {"Authorization": "Basic YWRtaW46YWRtaW4="},
        "expired": {"Authorization": f"Bearer {expired}"},
        "forged": {"Authorization": f"Bearer {forged}"},
        "unknown api token": {"Authorization": "Bearer bgrl_unknown"},
    }
    wrong_role_checked = 0
    for path, method, url in protected:
        role = _required_role(path, method)
        assert role is not None, f"{method.upper()} {path} has no auth dependency"
        for name, headers in bad_headers.items():
            response = api.client.request(method, url, headers=headers)
            assert response.status_code == 401, (name, method, path, response.text)
            assert response.json()["field"] == "token"
            assert response.headers["www-authenticate"] == "Bearer"
        if role != "viewer":
            weaker = "staff" if role == "admin" else "viewer"
            response = api.client.request(method, url, headers=api.as_(weaker))
            assert response.status_code == 403, (method, path, response.text)
            assert response.json() == {
                "detail": f"this needs the {role} role (you are {weaker})",
                "field": "role",
            }
            wrong_role_checked += 1
    assert wrong_role_checked >= 20


@pytest.mark.parametrize("path", ["/healthz", "/readyz", "/health"])
def test_health_routes_are_public(api: Api, path: str) -> None:
    response = api.client.get(path)
    assert response.status_code == 200
    assert response.json()["status"] in ("ok", "ready")


def test_readyz_names_the_revision(api: Api) -> None:
    from services.core.db.migrate import head_revision

    assert head_revision() == "0009"  # a new migration updates this line
    assert api.client.get("/readyz").json() == {"status": "ready", "database_revision": "0009"}


def test_readyz_reports_the_processes_bgrl_up_supervises(
    api: Api, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Under ``bgrl up``, /readyz lists each process; one restarting or stopped after a
    crash loop makes the platform 503 ``degraded``, naming it and why."""
    from services.core.db.migrate import head_revision

    status = tmp_path / "processes.json"
    monkeypatch.setattr(api.client.app.state.settings, "supervisor_status_file", status)
    running = {"kind": "sim", "state": "running", "pid": 7, "restarts": 2, "reason": None}
    status.write_text(json.dumps({"processes": {"sim": running}}))
    ready = api.client.get("/readyz")
    assert ready.status_code == 200
    assert ready.json()["status"] == "ready" and ready.json()["processes"] == {"sim": running}
    stopped = {**running, "state": "stopped", "pid": None, "reason": "crash loop: 5 exits"}
    status.write_text(json.dumps({"processes": {"sim": running, "worker-1": stopped}}))
    degraded = api.client.get("/readyz")
    assert degraded.status_code == 503
    assert degraded.json()["status"] == "degraded"
    assert degraded.json()["detail"] == "worker-1: crash loop: 5 exits"
    status.write_text("{not json")  # half-written or gone: the database decides alone
    assert api.client.get("/readyz").json() == {
        "status": "ready",
        "database_revision": head_revision(),
    }


def test_start_page_links_the_docs(api: Api) -> None:
    response = api.client.get("/")
    assert response.status_code == 200
    assert 'href="/docs"' in response.text


def test_deactivated_user_is_refused_at_once(api: Api) -> None:
    viewer_id = api.user_ids["viewer"]
    changed = api.client.patch(
        f"/api/v1/users/{viewer_id}", json={"active": False}, headers=api.as_("admin")
    )
    assert changed.status_code == 200
    response = api.client.get("/api/v1/subjects", headers=api.as_("viewer"))
    assert response.status_code == 401
    assert response.json() == {"detail": "account unknown or deactivated", "field": "token"}
