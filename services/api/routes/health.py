"""Liveness and readiness (no authentication); the start page is the dashboard's."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse
from sqlalchemy import text

from services.core.db.migrate import current_revision, head_revision

router = APIRouter(tags=["service"])


@router.get("/healthz")
async def healthz() -> dict[str, str]:
    """Liveness: the process answers (no per-request work, no database, no thread)."""
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
