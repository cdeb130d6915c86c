"""Websocket relay of a live session's robot frames to the dashboard.

The sim listens on loopback and wants the internal service token, so browsers cannot reach
it: ``WS /api/v1/sessions/{id}/frames`` checks the user's token (an ``Authorization``
header, or the subprotocols ``bgrl`` and ``bearer.<token>``) and the ``Origin`` before
``accept``, then opens the sim's frame stream of the
session's current sim session (``GET /sessions/{sim id}/stream``, JPEG, base64, a frame right
after every action) with the service token and forwards every message as it comes. Close
codes: 4401 unauthenticated and 4403 Origin refused (before ``accept``), 4404 unknown session
or no sim session yet (after ``accept``, so a signed-in page gets the code and retries), 1013
the sim is unreachable (the page reconnects); 4401 too when the token stops working while
frames flow (checked every half second).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from urllib.parse import quote

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from fastapi.concurrency import run_in_threadpool
from sqlalchemy import select
from websockets.asyncio.client import connect
from websockets.exceptions import WebSocketException

from services.api.deps import (
    until_signed_out,
    websocket_sign_in_refusal,
    websocket_subprotocol,
)
from services.core.db.live import LiveRun
from services.core.db.models import LabSession
from services.core.websockets import (
    CLOSE_NOT_FOUND,
    CLOSE_ORIGIN_REFUSED,
    close_reason,
    origin_allowed,
)

router = APIRouter(tags=["live sessions"])
logger = logging.getLogger(__name__)

CLOSE_TRY_AGAIN = 1013
FRAME_PARAMS = "fps=2&on_action=true&view=camera&format=jpeg&encoding=base64"


def _sim_session(websocket: WebSocket, session_id: int) -> tuple[int, str]:
    """``(0, sim session id)``, or ``(close code, reason)`` if the connection is refused."""
    with websocket.app.state.sessions() as db:
        if (refused := websocket_sign_in_refusal(db, websocket)) is not None:
            return refused
        if db.get(LabSession, session_id) is None:
            return CLOSE_NOT_FOUND, f"no session with id {session_id}"
        sim_id = db.scalar(
            select(LiveRun.sim_session_id)
            .where(LiveRun.session_id == session_id)
            .order_by(LiveRun.id.desc())
        )
    if sim_id is None:
        return CLOSE_NOT_FOUND, f"session {session_id} has no running sim session yet"
    return 0, sim_id


@router.websocket("/api/v1/sessions/{session_id}/frames")
async def frames(websocket: WebSocket, session_id: int) -> None:
    """The robot's frames of the session's live run as the sim renders them (see module)."""
    settings = websocket.app.state.settings
    if not origin_allowed(websocket, settings.allowed_origins):
        await websocket.close(code=CLOSE_ORIGIN_REFUSED, reason="origin not allowed")
        return
    code, detail = await run_in_threadpool(_sim_session, websocket, session_id)
    if code and code != CLOSE_NOT_FOUND:
        await websocket.close(code=code, reason=detail[:120])  # refused before accept
        return
    if not code and not settings.sim_url:
        code, detail = CLOSE_NOT_FOUND, "no sim service configured"
    await websocket.accept(subprotocol=websocket_subprotocol(websocket))
    if code:
        # Signed in, nothing to relay yet (the run's sim session is being opened): say so
        # with the close code; a refused handshake would reach the page as 1006 and an error.
        await websocket.close(code=code, reason=detail[:120])
        return
    base = settings.sim_url.rstrip("/").replace("http", "ws", 1)
    url = f"{base}/sessions/{quote(detail, safe='')}/stream?{FRAME_PARAMS}"
    headers = {"X-Service-Token": settings.service_token} if settings.service_token else {}
    try:
        async with connect(url, additional_headers=headers, max_size=None) as upstream:
            forward = asyncio.create_task(_forward(upstream, websocket))
            watch = asyncio.create_task(_until_client_leaves(websocket))
            signed_out = asyncio.create_task(until_signed_out(websocket))
            tasks = {forward, watch, signed_out}
            _, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            for task in pending:
                task.cancel()
        if signed_out.done() and not signed_out.cancelled():
            code, detail = signed_out.result()
            with contextlib.suppress(RuntimeError, WebSocketDisconnect):
                await websocket.close(code=code, reason=close_reason(detail))
            return
    except (OSError, WebSocketException) as exc:
        logger.info("frame relay of session %s: sim unreachable (%s)", session_id, exc)
        with contextlib.suppress(RuntimeError, WebSocketDisconnect):
            await websocket.send_json({"type": "error", "detail": "the sim is unreachable"})
            await websocket.close(code=CLOSE_TRY_AGAIN, reason="sim unreachable")
        return
    with contextlib.suppress(RuntimeError, WebSocketDisconnect):
        await websocket.close(code=1000)


async def _forward(upstream, websocket: WebSocket) -> None:  # type: ignore[no-untyped-def]
    async for message in upstream:
        if isinstance(message, bytes):
            await websocket.send_bytes(message)
        else:
            await websocket.send_text(message)


async def _until_client_leaves(websocket: WebSocket) -> None:
    while (await websocket.receive())["type"] != "websocket.disconnect":
        pass
