"""Live decoding: connect a source, classify markers, stream feedback.

HTTP: ``POST /live`` (connect an LSL EEG stream, optionally the sim's marker stream),
``GET /live`` (status, detected issues, background errors), ``DELETE /live``,
``POST /live/markers`` (classify the epoch after one action marker), ``POST`` and
``DELETE /live/recording`` (record the live stream and its markers; store it as a BDF).

Websockets (close codes, all with a reason):

* ``WS /live/feedback`` sends every decoded :class:`~services.eeg.service.schemas.Feedback`.
* ``WS /live/ingest?classifier_id=`` takes sample chunks from devices without LSL (without
  ``classifier_id``: recording only): first message ``{"ch_names": [...], "sfreq": 2048,
  "synthetic": false}``, then ``{"first_timestamp", "samples"}``
  messages, or binary messages (the first timestamp as a little-endian float64, then the
  samples as little-endian float32, time-major: no JSON to encode and parse, the way the
  accelerated virtual subject sends them), each answered ``{"ok": true, "n_samples": N}``
  or ``{"ok": false, "error"}``.
  An unknown classifier closes with 4404 after the handshake; a bad query
  parameter, or a first message that is not JSON or not a valid header, closes with 4422;
  a second ingest connection (or ``POST``/``DELETE /live``) replaces this one, which is
  closed with 4410.
* A foreign ``Origin`` is refused on both before the handshake completes (close 4403,
  which a browser sees as a failed handshake, HTTP 403).
"""

from __future__ import annotations

import asyncio
import logging
import struct
from contextlib import suppress
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Query, WebSocket, WebSocketDisconnect
from pydantic import ValidationError

from services.core.errors import ServiceError
from services.core.markers import ActionMarker
from services.core.web import validation_error_body
from services.core.websockets import (
    CLOSE_BAD_REQUEST,
    CLOSE_NOT_FOUND,
    CLOSE_ORIGIN_REFUSED,
    close_reason,
    origin_allowed,
)
from services.eeg.live.ingest import LiveIngest
from services.eeg.service.deps import ServiceDep, get_service
from services.eeg.service.errors import LiveSourceError, NoLiveSourceError
from services.eeg.service.live_session import LiveSession
from services.eeg.service.schemas import (
    Feedback,
    IngestChunk,
    IngestHeader,
    LiveConnect,
    LiveRecordingPublic,
    LiveRecordingStart,
    LiveStatus,
    RecordingPublic,
)
from services.eeg.service.state import EEGService

router = APIRouter(prefix="/live", tags=["live"])
logger = logging.getLogger(__name__)

CLOSE_REPLACED = 4410
"""Close code of an ingest websocket whose live session was replaced or disconnected."""
BINARY_HEADER_BYTES = 8
"""A binary ingest chunk starts with its first timestamp (float64)."""


def _status(service: EEGService) -> LiveStatus:
    session = service.live
    status = session.status() if session is not None else LiveStatus(connected=False)
    recorder = service.recorder
    status.recording = service.recording_status(recorder) if recorder is not None else None
    status.unfinished_recordings = service.unfinished_recordings()
    return status


@router.post("")
def connect_live(body: LiveConnect, service: ServiceDep) -> LiveStatus:
    """Connect an LSL EEG stream, checked against the classifier's channels and rate.

    With ``marker_stream``, every marker of that LSL stream is classified as it arrives and
    the feedback goes to ``WS /live/feedback``. Without ``classifier_id`` nothing is decoded:
    the stream and its markers can only be recorded (calibration). Replaces the current
    live source.
    """
    from services.eeg.live import lsl  # loads liblsl (mne_lsl): only when a stream connects

    settings = service.settings
    clf = service.classifiers.get(body.classifier_id) if body.classifier_id else None
    try:
        source = lsl.LslEegIngest(
            body.stream_name,
            eeg_ch_names=clf.ch_names if clf else None,
            channel_map=body.channel_map,
            params=clf.params if clf else None,
            timeout=settings.lsl_timeout_s,
        )
    except (RuntimeError, ValueError) as exc:
        raise LiveSourceError(str(exc), field="stream_name") from None
    session = LiveSession(
        source.ingest,
        clf,
        body.classifier_id,
        "lsl",
        stream_name=body.stream_name,
        eeg_source=source,
        synthetic=source.synthetic,
    )
    try:
        try:
            if clf is not None:
                clf.check_compatible(source.ingest.eeg_ch_names, source.ingest.sfreq)
        except ValueError as exc:
            raise LiveSourceError(
                f"stream {body.stream_name!r}: {exc}", field="stream_name"
            ) from None
        if body.marker_stream is not None:
            try:
                inlet = lsl.MarkerInlet(body.marker_stream, timeout=settings.lsl_timeout_s)
            except RuntimeError as exc:
                raise LiveSourceError(str(exc), field="marker_stream") from None
            session.follow_markers(inlet, body.marker_stream, service.hub, settings.epoch_wait_s)
    except BaseException:
        session.close("connection refused")
        raise
    service.set_live(session, f"replaced by the LSL stream {body.stream_name!r}")
    logger.info("live source: LSL stream %r, classifier %s", body.stream_name, body.classifier_id)
    return session.status()


@router.get("")
def live_status(service: ServiceDep) -> LiveStatus:
    """The live source, the problems detected in it, and any background failure."""
    return _status(service)


@router.delete("")
def disconnect_live(service: ServiceDep) -> LiveStatus:
    """Disconnect the live source (an ingest websocket is closed with 4410)."""
    service.set_live(None, "disconnected by DELETE /live")
    return _status(service)


@router.post("/recording", status_code=201)
def start_recording(body: LiveRecordingStart, service: ServiceDep) -> LiveRecordingPublic:
    """Record the live stream and every marker to disk as they arrive (flushed each second).

    The name of a recording interrupted by a crash continues it (one already stored starts
    anew). 409 while another recording runs or when there is no live source.
    """
    return service.start_recording(body.name)


@router.delete("/recording")
def stop_recording(
    service: ServiceDep,
    name: Annotated[
        str | None, Query(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
    ] = None,
) -> RecordingPublic:
    """Stop the live recording and store it as a BDF (Status: 1 correct, 2 error).

    With ``name`` and no recording in progress, finalise that interrupted recording; if it
    was already stored (the service stopped before removing its folder), answer the stored
    recording.
    """
    return service.stop_recording(name)


@router.post("/markers")
def classify_marker(marker: ActionMarker, service: ServiceDep) -> Feedback:
    """Classify the epoch after an action marker (LSL clock) from the live stream."""
    session = service.live
    if session is None or session.closed:
        raise NoLiveSourceError("no live EEG source: POST /live or open WS /live/ingest first")
    feedback = session.classify_marker(marker, service.settings.epoch_wait_s)
    service.hub.broadcast(feedback.model_dump(mode="json"))
    return feedback


async def _close(websocket: WebSocket, code: int, detail: str) -> None:
    """Tell the client why (one message), then close with ``code`` and the reason."""
    with suppress(WebSocketDisconnect, RuntimeError):
        await websocket.send_json({"ok": False, "error": detail})
        await websocket.close(code=code, reason=close_reason(detail))


@router.websocket("/feedback")
async def feedback_socket(websocket: WebSocket) -> None:
    """Every decoded feedback, as JSON messages (:class:`Feedback`)."""
    service = get_service(websocket)
    if not origin_allowed(websocket, service.settings.allowed_origins):
        await websocket.close(code=CLOSE_ORIGIN_REFUSED, reason="origin not allowed")
        return
    await websocket.accept()
    queue = service.hub.subscribe()
    receiver = asyncio.create_task(websocket.receive())
    getter = asyncio.create_task(queue.get())
    try:
        while True:
            done, _ = await asyncio.wait({getter, receiver}, return_when=asyncio.FIRST_COMPLETED)
            if receiver in done:
                if receiver.result()["type"] == "websocket.disconnect":
                    return
                receiver = asyncio.create_task(websocket.receive())  # client messages: ignored
            if getter in done:
                await websocket.send_json(getter.result())
                getter = asyncio.create_task(queue.get())
    except WebSocketDisconnect:
        pass
    finally:
        service.hub.unsubscribe(queue)
        receiver.cancel()
        getter.cancel()


def _parse_header(message: dict[str, Any]) -> IngestHeader:
    text = message.get("text")
    if text is None:
        raise ValueError("the first message must be a JSON text message")
    try:
        return IngestHeader.model_validate_json(text)
    except ValidationError as exc:
        errors = exc.errors()
        if errors and errors[0]["type"] == "json_invalid":
            raise ValueError(f"the first message is not JSON: {text[:40]!r}") from None
        raise ValueError("bad header: " + validation_error_body(errors)["message"]) from None


def _binary_chunk(data: bytes, n_channels: int) -> tuple[np.ndarray, float]:
    """A binary chunk: little-endian float64 first timestamp, then float32 samples,
    time-major (n_times x n_channels)."""
    row = 4 * n_channels
    if len(data) < BINARY_HEADER_BYTES + row or (len(data) - BINARY_HEADER_BYTES) % row:
        raise ValueError(
            f"a binary chunk is 8 bytes (float64 first_timestamp) and n_times x {n_channels} "
            f"float32 samples; got {len(data)} bytes"
        )
    (first,) = struct.unpack_from("<d", data)
    samples = np.frombuffer(data, dtype="<f4", offset=BINARY_HEADER_BYTES).reshape(-1, n_channels)
    return samples.astype(np.float64), first


def _ingest_chunk(ingest: LiveIngest, message: dict[str, Any]) -> dict[str, Any]:
    data, text = message.get("bytes"), message.get("text")
    try:
        if data is not None:
            samples, first = _binary_chunk(data, len(ingest.stream_ch_names))
        elif text is not None:
            chunk = IngestChunk.model_validate_json(text)
            n_channels = len(ingest.stream_ch_names)
            ragged = next(
                (i for i, row in enumerate(chunk.samples) if len(row) != n_channels), None
            )
            if ragged is not None:
                return {
                    "ok": False,
                    "error": f"samples: each row holds one value per channel ({n_channels}); "
                    f"row {ragged} holds {len(chunk.samples[ragged])}",
                }
            samples = np.asarray(chunk.samples, dtype=np.float64)
            first = chunk.first_timestamp
        else:
            return {"ok": False, "error": "send JSON text or binary messages"}
    except ValidationError as exc:
        errors = exc.errors()
        if errors and errors[0]["type"] == "json_invalid":
            return {"ok": False, "error": f"not JSON: {(text or '')[:40]!r}"}
        return {"ok": False, "error": validation_error_body(errors)["message"]}
    except ValueError as exc:
        return {"ok": False, "error": str(exc)}
    try:
        ingest.push_chunk(samples, first_timestamp=first)
    except ValueError as exc:
        return {"ok": False, "error": str(exc)}
    return {"ok": True, "n_samples": ingest.n_samples}


@router.websocket("/ingest")
async def ingest_socket(
    websocket: WebSocket,
    classifier_id: Annotated[str | None, Query(min_length=1, max_length=64)] = None,
) -> None:
    """Sample chunks from a device without LSL (protocol in the module docstring)."""
    service = get_service(websocket)
    if not origin_allowed(websocket, service.settings.allowed_origins):
        await websocket.close(code=CLOSE_ORIGIN_REFUSED, reason="origin not allowed")
        return
    await websocket.accept()
    try:
        clf = (
            await asyncio.to_thread(service.classifiers.get, classifier_id)
            if classifier_id
            else None
        )
    except ServiceError as exc:
        code = CLOSE_NOT_FOUND if exc.status_code == 404 else CLOSE_BAD_REQUEST
        await _close(websocket, code, str(exc))
        return
    try:
        first = await websocket.receive()
        if first["type"] == "websocket.disconnect":
            return
        header = _parse_header(first)
        ingest = LiveIngest(
            header.ch_names,
            header.sfreq,
            eeg_ch_names=clf.ch_names if clf else None,
            params=clf.params if clf else None,
        )
        if clf is not None:
            clf.check_compatible(ingest.eeg_ch_names, header.sfreq)
    except ValueError as exc:
        await _close(websocket, CLOSE_BAD_REQUEST, str(exc))
        return

    session = LiveSession(ingest, clf, classifier_id, "websocket", synthetic=header.synthetic)
    loop = asyncio.get_running_loop()
    replaced = asyncio.Event()

    def wake() -> None:
        with suppress(RuntimeError):  # the loop is closed: the service is stopping
            loop.call_soon_threadsafe(replaced.set)

    session.on_close(wake)
    await asyncio.to_thread(service.set_live, session, "replaced by a new WS /live/ingest")
    logger.info("live source: websocket ingest, classifier %s", classifier_id)
    waiter = asyncio.create_task(replaced.wait())
    try:
        await websocket.send_json({"ok": True, "n_samples": 0})
        while True:
            receiver = asyncio.create_task(websocket.receive())
            await asyncio.wait({receiver, waiter}, return_when=asyncio.FIRST_COMPLETED)
            if not receiver.done():
                receiver.cancel()
                await _close(websocket, CLOSE_REPLACED, session.close_reason or "closed")
                return
            message = receiver.result()
            if message["type"] == "websocket.disconnect":
                return
            await websocket.send_json(_ingest_chunk(ingest, message))
    except WebSocketDisconnect:
        pass
    finally:
        waiter.cancel()
        ingest.mark_disconnected("websocket closed")
