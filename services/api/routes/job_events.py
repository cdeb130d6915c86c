"""Job progress pushed over a websocket (token and Origin checked before ``accept``)."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from fastapi.concurrency import run_in_threadpool

from services.api.crud import get_row
from services.api.deps import (
    REVOCATION_CHECK_S,
    websocket_sign_in_refusal,
    websocket_subprotocol,
)
from services.api.schemas.jobs import JobPublic
from services.core.db.models import JOB_FINAL_STATUSES, Job
from services.core.websockets import (
    CLOSE_NOT_FOUND,
    CLOSE_ORIGIN_REFUSED,
    close_reason,
    origin_allowed,
)

router = APIRouter(tags=["jobs"])

POLL_S = REVOCATION_CHECK_S
"""The job is read, and its token checked, this often."""


def _check(websocket: WebSocket, job_id: str) -> tuple[int, str] | None:
    """``(close code, reason)`` if the connection is refused, else None."""
    with websocket.app.state.sessions() as db:
        if (refused := websocket_sign_in_refusal(db, websocket)) is not None:
            return refused
        if get_row(db, Job, job_id) is None:
            return CLOSE_NOT_FOUND, f"no job with id {job_id}"
    return None


def _snapshot(websocket: WebSocket, job_id: str) -> dict | tuple[int, str]:
    """The job as ``GET /api/v1/jobs/{id}`` gives it, or ``(close code, reason)`` when its
    token stopped working or the job is gone."""
    with websocket.app.state.sessions() as db:
        if (refused := websocket_sign_in_refusal(db, websocket)) is not None:
            return refused
        job = db.get(Job, job_id)
        if job is None:
            return CLOSE_NOT_FOUND, "job deleted"
        return JobPublic.model_validate(job).model_dump(mode="json")


@router.websocket("/api/v1/jobs/{job_id}/events")
async def job_events(websocket: WebSocket, job_id: str) -> None:
    """Sends the job (as ``GET /api/v1/jobs/{id}``) whenever it changes; closes when it ends.

    Authenticate with an ``Authorization: Bearer`` header or, from a browser, by offering
    the subprotocols ``bgrl`` and ``bearer.<token>`` (a token in the URL is refused). The
    token is checked every half second: a revoked or expired one closes the socket (4401).
    Close codes: 4401 unauthenticated, 4403 Origin refused, 4404 unknown job.
    """
    if not origin_allowed(websocket, websocket.app.state.settings.allowed_origins):
        await websocket.close(code=CLOSE_ORIGIN_REFUSED, reason="origin not allowed")
        return
    refused = await run_in_threadpool(_check, websocket, job_id)
    if refused is not None:
        await websocket.close(code=refused[0], reason=close_reason(refused[1]))
        return
    await websocket.accept(subprotocol=websocket_subprotocol(websocket))
    last_update = None
    try:
        while True:
            job = await run_in_threadpool(_snapshot, websocket, job_id)
            if isinstance(job, tuple):
                await websocket.close(code=job[0], reason=close_reason(job[1]))
                return
            if job["updated_at"] != last_update:
                last_update = job["updated_at"]
                await websocket.send_json(job)
            if job["status"] in JOB_FINAL_STATUSES:
                await websocket.close(code=1000)
                return
            await asyncio.sleep(POLL_S)
    except WebSocketDisconnect:
        return
