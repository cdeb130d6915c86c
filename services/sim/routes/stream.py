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
from typing import Annotated, Any
from urllib.parse import urlsplit

from fastapi import APIRouter, Query, WebSocket, WebSocketDisconnect, status
from starlette.concurrency import run_in_threadpool

from services.sim.deps import get_registry, get_settings
from services.sim.errors import SessionClosedError, SessionNotFoundError
from services.sim.imaging import encode_image
from services.sim.lsl_markers import lsl_clock
from services.sim.schemas import FrameEncoding, FrameFormat, SessionPublic
from services.sim.sessions import FrameView, SimSession
from services.sim.settings import SimSettings

MAX_FPS = 30.0
"""Upper bound of the frame rate, also when frames follow actions."""

router = APIRouter(tags=["stream"])
logger = logging.getLogger(__name__)

CLOSE_UNKNOWN_SESSION = 4404
CLOSE_SESSION_CLOSED = 4410


def origin_allowed(websocket: WebSocket, settings: SimSettings) -> bool:
    """Same-host origins, configured origins, and clients that send no Origin (not browsers)."""
    origin = websocket.headers.get("origin")
    if origin is None:
        return True
    if origin in settings.allowed_origins:
        return True
    host = websocket.headers.get("host", "")
    return bool(host) and urlsplit(origin).netloc.lower() == host.lower()


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
async def stream_frames(
    websocket: WebSocket,
    session_id: str,
    fps: Annotated[float | None, Query(ge=1.0, le=MAX_FPS)] = None,
    on_action: Annotated[bool, Query()] = True,
    view: Annotated[FrameView, Query()] = "camera",
    image_format: Annotated[FrameFormat, Query(alias="format")] = "jpeg",
    encoding: Annotated[FrameEncoding, Query()] = "base64",
) -> None:
    """Stream frames plus state at ``fps`` until the client leaves or the session closes."""
    settings = get_settings(websocket)
    if not origin_allowed(websocket, settings):
        await websocket.close(code=status.WS_1008_POLICY_VIOLATION)
        return
    await websocket.accept()
    try:
        session = get_registry(websocket).get(session_id)
    except (SessionClosedError, SessionNotFoundError) as exc:
        code = (
            CLOSE_SESSION_CLOSED if isinstance(exc, SessionClosedError) else CLOSE_UNKNOWN_SESSION
        )
        await websocket.send_json({"type": "error", "detail": str(exc)})
        await websocket.close(code=code, reason=str(exc)[:120])
        return
    sender = asyncio.create_task(
        _send_frames(
            websocket,
            session,
            settings,
            fps=fps or settings.frame_rate_fps,
            on_action=on_action,
            view=view,
            image_format=image_format,
            encoding=encoding,
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
