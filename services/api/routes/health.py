"""Liveness, readiness and the start page (no authentication)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import HTMLResponse, JSONResponse
from sqlalchemy import text

from services.core.db.migrate import current_revision, head_revision

router = APIRouter(tags=["service"])

START_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Brain-guided RL platform</title></head>
<body><h1>Brain-guided RL platform</h1>
<p>REST API under <code>/api/v1</code>: <a href="/docs">interactive docs</a>,
<a href="/openapi.json">OpenAPI schema</a>. Sign in with
<code>POST /api/v1/auth/token</code>.</p></body></html>
"""


@router.get("/", response_class=HTMLResponse, include_in_schema=False)
def start_page() -> str:
    """A plain page linking the API docs."""
    return START_PAGE


@router.get("/healthz")
def healthz() -> dict[str, str]:
    """Liveness: the process answers."""
    return {"status": "ok"}


@router.get("/readyz", responses={503: {"description": "Database unreachable or not migrated"}})
def readyz(request: Request) -> Any:
    """Readiness: the database answers and is at the newest migration."""
    engine = request.app.state.engine
    try:
        with engine.connect() as connection:
            connection.execute(text("SELECT 1"))
        revision = current_revision(engine)
    except Exception as exc:
        return JSONResponse(
            status_code=503, content={"status": "unavailable", "detail": type(exc).__name__}
        )
    head = head_revision()
    if revision != head:
        return JSONResponse(
            status_code=503,
            content={"status": "unavailable", "detail": f"database at {revision}, code at {head}"},
        )
    return {"status": "ready", "database_revision": revision}
