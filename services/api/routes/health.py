"""Liveness and readiness (no authentication); the start page is the dashboard's."""

from __future__ import annotations

import json
from pathlib import Path
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


def supervised_processes(status_file: Path | None) -> dict[str, Any] | None:
    """The processes ``bgrl up`` supervises (its status file), None if it did not start us."""
    if status_file is None:
        return None
    try:
        processes = json.loads(status_file.read_text())["processes"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return processes if isinstance(processes, dict) else None


@router.get(
    "/readyz",
    responses={
        503: {
            "description": "Database unreachable or not migrated, or (under `bgrl up`) a "
            "process of the platform restarting or stopped after a crash loop"
        }
    },
)
def readyz(request: Request) -> Any:
    """Readiness: the database answers and is at the newest migration; under ``bgrl up``,
    every process of the platform runs (``processes``: state, restarts, last exit of each)."""
    processes = supervised_processes(request.app.state.settings.supervisor_status_file)
    extra = {} if processes is None else {"processes": processes}
    engine = request.app.state.engine
    try:
        with engine.connect() as connection:
            connection.execute(text("SELECT 1"))
        revision = current_revision(engine)
    except Exception as exc:
        return JSONResponse(
            status_code=503,
            content={"status": "unavailable", "detail": type(exc).__name__, **extra},
        )
    head = head_revision()
    if revision != head:
        return JSONResponse(
            status_code=503,
            content={
                "status": "unavailable",
                "detail": f"database at {revision}, code at {head}",
                **extra,
            },
        )
    down = [
        f"{name}: {p.get('reason') or p.get('state')}"
        for name, p in (processes or {}).items()
        if isinstance(p, dict) and p.get("state") in ("restarting", "stopped")
    ]
    if down:
        return JSONResponse(
            status_code=503,
            content={
                "status": "degraded",
                "detail": "; ".join(down),
                "database_revision": revision,
                **extra,
            },
        )
    return {"status": "ready", "database_revision": revision, **extra}
