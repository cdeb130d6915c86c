"""The frame stream: a websocket that sends frames plus state at a fixed rate.

The stream is decoupled from stepping: it samples the session's state and renders a frame
``fps`` times per second whatever the step rate (a step never waits for a client, and a
slow client only lowers its own frame rate). With ``on_action`` (default) it also sends a
frame as soon as an action has been executed, so that an observer sees the action with
the least delay (ErrP timing); frames never exceed 30 fps. Query parameters:

- ``fps``: periodic frames per second, 1-30 (default ``BGRL_SIM_FRAME_RATE_FPS``, 5);
- ``on_action``: ``true``/``false``, also send a frame right after each step or reset;
- ``view``: ``camera`` (third-person pybullet frame) or ``topdown`` (map with trajectory);
- ``format``: ``jpeg`` or ``png``;
- ``encoding``: ``base64`` (one JSON text message per frame, image in ``frame.data``) or
  ``binary`` (a JSON text message without ``data``, then one binary message with the image).

Each JSON message is ``{"type": "frame", "seq", "lsl_time", "state": <SessionPublic>,
"frame": {"format", "view", "width", "height", "bytes", "data"?}}``; ``lsl_time`` is when
the frame was rendered and ``state.last_marker`` the action it shows. When the session closes the
server sends ``{"type": "closed", "detail"}`` and closes with code 4410; an unknown session
gets close code 4404. A connection from a foreign ``Origin`` is refused before the handshake
completes (HTTP 403).
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import logging
import math
import time
from typing import Any

from fastapi import APIRouter, WebSocket, WebSocketDisconnect, status
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool

from services.core.web import validation_error_body
from services.core.websockets import (
    CLOSE_BAD_REQUEST,
    CLOSE_NOT_FOUND,
    CLOSE_ORIGIN_REFUSED,
    close_reason,
    origin_allowed,
)
from services.sim.deps import get_registry, get_settings
from services.sim.errors import SessionClosedError, SessionNotFoundError
from services.sim.imaging import encode_image
from services.sim.lsl_markers import lsl_clock
from services.sim.schemas import (
    MAX_FPS,
    FrameEncoding,
    FrameFormat,
    SessionPublic,
    StreamParams,
)
from services.sim.sessions import FrameView, SimSession
from services.sim.settings import SimSettings

router = APIRouter(tags=["stream"])
logger = logging.getLogger(__name__)

CLOSE_SESSION_CLOSED = 4410
"""Close code when the streamed session is (or gets) closed."""


def _frame_message(
    session: SimSession,
    settings: SimSettings,
    view: FrameView,
    image_format: FrameFormat,
    seq: int,
) -> tuple[dict[str, Any], bytes]:
    """Render and encode one frame with the state it shows (runs in a worker thread)."""
    snapshot, image = session.render_with_state(view)
    state = SessionPublic.model_validate(snapshot).model_dump(mode="json")
    data = encode_image(image, image_format, jpeg_quality=settings.jpeg_quality)
    message = {
        "type": "frame",
        "seq": seq,
        "lsl_time": lsl_clock(),
        "state": state,
        "frame": {
            "format": image_format,
            "view": view,
            "width": int(image.shape[1]),
            "height": int(image.shape[0]),
            "bytes": len(data),
        },
    }
    return message, data


async def _send_frames(
    websocket: WebSocket,
    session: SimSession,
    settings: SimSettings,
    *,
    fps: float,
    on_action: bool,
    view: FrameView,
    image_format: FrameFormat,
    encoding: FrameEncoding,
) -> None:
    period = 1.0 / fps
    loop = asyncio.get_running_loop()
    changed = asyncio.Event()

    def on_change() -> None:
        with contextlib.suppress(RuntimeError):  # the loop already closed: nothing to wake
            loop.call_soon_threadsafe(changed.set)

    if on_action:
        session.add_listener(on_change)
    seq = 0
    last_sent = -math.inf
    try:
        while True:
            # Never faster than MAX_FPS, even when actions come faster than that.
            await asyncio.sleep(max(0.0, last_sent + 1.0 / MAX_FPS - time.monotonic()))
            changed.clear()
            last_sent = time.monotonic()
            try:
                message, data = await run_in_threadpool(
                    _frame_message, session, settings, view, image_format, seq
                )
            except (SessionClosedError, SessionNotFoundError) as exc:
                await websocket.send_json({"type": "closed", "detail": str(exc)})
                await websocket.close(code=CLOSE_SESSION_CLOSED, reason="session closed")
                return
            except Exception as exc:
                logger.exception("frame stream of session %s failed", session.id)
                detail = f"rendering failed: {type(exc).__name__}: {exc}"
                await websocket.send_json({"type": "error", "detail": detail})
                await websocket.close(code=status.WS_1011_INTERNAL_ERROR, reason="rendering failed")
                return
            if encoding == "base64":
                message["frame"]["data"] = base64.b64encode(data).decode("ascii")
                await websocket.send_json(message)
            else:
                await websocket.send_json(message)
                await websocket.send_bytes(data)
            seq += 1
            # Next frame: one period after this one, or right after the next action.
            wait = last_sent + period - time.monotonic()
            if wait > 0:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(changed.wait(), timeout=wait)
    finally:
        session.remove_listener(on_change)


async def _wait_for_disconnect(websocket: WebSocket) -> None:
    while True:
        message = await websocket.receive()
        if message["type"] == "websocket.disconnect":
            return


@router.websocket("/sessions/{session_id}/stream")
async def stream_frames(websocket: WebSocket, session_id: str) -> None:
    """Stream frames plus state at ``fps`` until the client leaves or the session closes.

    Query parameters: :class:`services.sim.schemas.StreamParams` (``fps``, ``on_action``,
    ``view``, ``format``, ``encoding``).
    """
    settings = get_settings(websocket)
    if not origin_allowed(websocket, settings.allowed_origins):
        await websocket.close(code=CLOSE_ORIGIN_REFUSED, reason="origin not allowed")
        return
    await websocket.accept()
    try:
        params = StreamParams.model_validate(dict(websocket.query_params))
    except ValidationError as exc:
        body = validation_error_body(exc.errors())
        fields = ", ".join(dict.fromkeys(e["field"] for e in body["detail"]))
        await websocket.send_json({"type": "error", "detail": body["message"], "field": fields})
        await websocket.close(code=CLOSE_BAD_REQUEST, reason=close_reason(body["message"]))
        return
    try:
        session = get_registry(websocket).get(session_id)
    except (SessionClosedError, SessionNotFoundError) as exc:
        code = CLOSE_SESSION_CLOSED if isinstance(exc, SessionClosedError) else CLOSE_NOT_FOUND
        await websocket.send_json({"type": "error", "detail": str(exc)})
        await websocket.close(code=code, reason=close_reason(str(exc)))
        return
    sender = asyncio.create_task(
        _send_frames(
            websocket,
            session,
            settings,
            fps=params.fps or settings.frame_rate_fps,
            on_action=params.on_action,
            view=params.view,
            image_format=params.image_format,
            encoding=params.encoding,
        )
    )
    watcher = asyncio.create_task(_wait_for_disconnect(websocket))
    done, pending = await asyncio.wait({sender, watcher}, return_when=asyncio.FIRST_COMPLETED)
    for task in pending:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, WebSocketDisconnect, RuntimeError):
            await task
    for task in done:
        with contextlib.suppress(WebSocketDisconnect, RuntimeError):
            task.result()
