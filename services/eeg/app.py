"""The EEG service: recordings, calibration jobs, classifiers, live decoding.

Run with ``uvicorn services.eeg.app:app --port 8002`` (or ``bgrl serve``); configuration
comes from ``BGRL_EEG_*`` (:class:`~services.eeg.settings.EEGSettings`).

Resources (JSON unless stated):

* ``POST /recordings?filename=NAME.bdf`` (body: the file's bytes) validates and stores a
  BDF/EDF/FIF recording under its sha256 (201; 200 if already stored; 413 over the size
  limit; 422 naming the problem). ``GET /recordings``, ``GET /recordings/{id}``.
* ``POST /jobs`` ``{"recording_id", "seed", "max_epochs"}`` starts calibration training in
  the background (202); ``GET /jobs``, ``GET /jobs/{id}`` report its state.
* ``GET /classifiers`` lists trained classifiers with their metrics;
  ``POST /classifiers/{id}/classify`` classifies one preprocessed epoch
  ``{"epoch": [[...]], "ch_names": [...], "sfreq": 128}``.
* ``POST /live`` ``{"classifier_id", "stream_name", "marker_stream"}`` connects an LSL EEG
  stream and optionally the sim's LSL marker stream, whose markers are then classified as
  they come (``GET /live``: status and detected stream problems; ``DELETE /live``: stop);
  ``WS /live/ingest?classifier_id=...`` takes sample chunks from devices without LSL;
  ``POST /live/markers`` (an :class:`~services.core.markers.ActionMarker`) classifies the
  epoch after an action; ``WS /live/feedback`` streams every decoded feedback.

Everything written is first written to a temporary name and renamed, so a failure never
leaves a half-written recording, classifier or job record behind.
"""

from __future__ import annotations

import asyncio
import datetime
import json
import os
import shutil
import tempfile
import threading
import uuid
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager, suppress
from pathlib import Path
from typing import Annotated, Any, Literal
from urllib.parse import urlsplit

import numpy as np
from fastapi import APIRouter, Depends, FastAPI, HTTPException, Query, Request, WebSocket
from fastapi.responses import JSONResponse
from fastapi.websockets import WebSocketDisconnect
from pydantic import BaseModel, Field
from starlette.requests import HTTPConnection

from services.core.markers import ActionMarker
from services.eeg.io import (
    SUPPORTED_SUFFIXES,
    RecordingError,
    action_events,
    file_sha256,
    is_synthetic,
    read_recording,
)
from services.eeg.live import EpochResult, LiveIngest
from services.eeg.settings import EEGSettings

CHUNK_BYTES = 1 << 20


# ---------------------------------------------------------------------------- schemas
class RecordingPublic(BaseModel):
    """A stored, validated recording."""

    id: str = Field(description="The file's sha256 (hex).")
    filename: str
    format: str
    sha256: str
    size_bytes: int
    sfreq: float
    n_channels: int
    duration_s: float
    n_actions: int
    n_errors: int
    synthetic: bool
    uploaded_at: str


class JobCreate(BaseModel):
    """Start calibration training on a stored recording."""

    recording_id: str = Field(min_length=8, max_length=64, pattern="^[0-9a-f]+$")
    seed: int = Field(0, ge=0, le=2**31 - 1)
    max_epochs: int = Field(300, ge=1)


class JobPublic(BaseModel):
    """A calibration job and, once done, the classifier it produced."""

    id: str
    recording_id: str
    seed: int
    max_epochs: int
    state: Literal["queued", "running", "done", "failed"]
    created_at: str
    finished_at: str | None = None
    classifier_id: str | None = None
    error: str | None = None
    metrics: dict[str, Any] | None = None


class ClassifierPublic(BaseModel):
    """A trained ErrP classifier."""

    id: str
    recording_id: str | None
    synthetic: bool
    ch_names: list[str]
    sfreq_in: float
    epoch_shape: tuple[int, int]
    metrics: dict[str, Any]


class EpochClassify(BaseModel):
    """One preprocessed epoch (volts), channels x times."""

    epoch: list[list[float]]
    ch_names: list[str] = Field(description="Channel of each row, in order.")
    sfreq: float = Field(gt=0, description="Sampling rate of the epoch (the features' rate).")


class Feedback(BaseModel):
    """Decoded feedback for one action (or why there is none)."""

    status: Literal["ok", "rejected"]
    p_error: float | None = None
    feedback: Literal["correct", "error"] | None = None
    reason: str | None = None
    onset: float | None = None
    step: int | None = None
    session_id: str | None = None
    classifier_id: str
    synthetic: bool


class LiveConnect(BaseModel):
    """Connect an LSL EEG stream for live decoding."""

    classifier_id: str = Field(min_length=1, max_length=64)
    stream_name: str = Field("BrainNav-EEG", min_length=1, max_length=200)
    marker_stream: str | None = Field(
        None,
        min_length=1,
        max_length=200,
        description="Also classify every marker of this LSL marker stream (the sim's is "
        "BrainNav-Markers); otherwise markers come through POST /live/markers.",
    )


class LiveStatus(BaseModel):
    """The live source and what its integrity checks found."""

    connected: bool
    source: Literal["lsl", "websocket"] | None = None
    classifier_id: str | None = None
    stream_name: str | None = None
    marker_stream: str | None = None
    n_samples: int = 0
    latest_timestamp: float | None = None
    issues: list[dict[str, Any]] = Field(default_factory=list)


# ------------------------------------------------------------------------------ state
def _now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def _write_json(path: Path, payload: dict[str, Any]) -> None:
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    tmp.write_text(json.dumps(payload, indent=2))
    tmp.replace(path)


class LiveSession:
    """The live source (LSL inlet or websocket) bound to one classifier."""

    def __init__(
        self,
        ingest: LiveIngest,
        classifier: Any,
        classifier_id: str,
        source: Literal["lsl", "websocket"],
        *,
        stream_name: str | None = None,
        lsl: Any = None,
    ) -> None:
        self.ingest = ingest
        self.classifier = classifier
        self.classifier_id = classifier_id
        self.source = source
        self.stream_name = stream_name
        self.lsl = lsl
        self.marker_stream: str | None = None
        self._stop = threading.Event()
        self._marker_thread: threading.Thread | None = None

    def follow_markers(self, service: EEGService, marker_stream: str, timeout: float) -> None:
        """Classify every marker of the sim's LSL marker stream, broadcasting the feedback."""
        from services.eeg.lsl import MarkerInlet

        inlet = MarkerInlet(marker_stream, timeout=timeout)
        self.marker_stream = marker_stream

        def run() -> None:
            try:
                while not self._stop.is_set():
                    try:
                        markers = inlet.pull(timeout=0.1)
                    except ValueError:
                        continue  # a malformed marker is skipped
                    for marker in markers:
                        result = self.ingest.wait_epoch(
                            marker.timestamp, timeout_s=service.settings.epoch_wait_s
                        )
                        service.broadcast(service.decode(result, marker, self).model_dump())
            finally:
                inlet.close()

        self._marker_thread = threading.Thread(target=run, name="lsl-markers", daemon=True)
        self._marker_thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._marker_thread is not None:
            self._marker_thread.join(timeout=2.0)
        if self.lsl is not None:
            self.lsl.close()
        else:
            self.ingest.mark_disconnected("websocket closed")


class EEGService:
    """Stores, jobs, classifier cache and the live session of one app instance."""

    def __init__(self, settings: EEGSettings) -> None:
        self.settings = settings
        root = settings.eeg_dir
        self.recordings_dir = root / "recordings"
        self.classifiers_dir = root / "classifiers"
        self.jobs_dir = root / "jobs"
        for folder in (self.recordings_dir, self.classifiers_dir, self.jobs_dir):
            folder.mkdir(parents=True, exist_ok=True)
        self.executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="calibration")
        self._lock = threading.Lock()
        self._classifiers: dict[str, Any] = {}
        self.live: LiveSession | None = None
        self.subscribers: set[asyncio.Queue[dict[str, Any]]] = set()
        self.loop: asyncio.AbstractEventLoop | None = None
        self.fail_interrupted_jobs()

    # recordings
    def recording(self, recording_id: str) -> RecordingPublic:
        path = self.recordings_dir / f"{recording_id}.json"
        if not recording_id.isalnum() or not path.is_file():
            raise HTTPException(404, f"no recording {recording_id!r}")
        return RecordingPublic.model_validate_json(path.read_text())

    def recording_file(self, recording_id: str) -> Path:
        meta = self.recording(recording_id)
        return self.recordings_dir / f"{meta.sha256}.{meta.format}"

    # jobs
    def job(self, job_id: str) -> JobPublic:
        path = self.jobs_dir / f"{job_id}.json"
        if not job_id.isalnum() or not path.is_file():
            raise HTTPException(404, f"no job {job_id!r}")
        return JobPublic.model_validate_json(path.read_text())

    def fail_interrupted_jobs(self) -> None:
        """Mark jobs a previous process left queued or running as failed, with the reason.

        The executor lives in this process, so such a job can never finish; its half-written
        classifier folder is removed and the recording stays stored for a new job.
        """
        for path in self.jobs_dir.glob("*.json"):
            job = JobPublic.model_validate_json(path.read_text())
            if job.state in ("queued", "running"):
                shutil.rmtree(self.classifiers_dir / f".{job.id}.part", ignore_errors=True)
                self.save_job(
                    job.model_copy(
                        update={
                            "state": "failed",
                            "error": "interrupted: the EEG service stopped before the job "
                            "finished; start a new job",
                            "finished_at": _now(),
                        }
                    )
                )

    def save_job(self, job: JobPublic) -> None:
        _write_json(self.jobs_dir / f"{job.id}.json", job.model_dump())

    def run_job(self, job: JobPublic) -> None:
        """Train a classifier (in the worker thread); the job record tells the outcome."""
        import torch

        from services.eeg.calibration import TrainingConfig, calibrate

        torch.set_num_threads(1)
        job = job.model_copy(update={"state": "running"})
        self.save_job(job)
        staging = self.classifiers_dir / f".{job.id}.part"
        try:
            raw = read_recording(self.recording_file(job.recording_id))
            result = calibrate(
                raw,
                seed=job.seed,
                out_dir=staging,
                config=TrainingConfig(max_epochs=job.max_epochs),
                report=True,
            )
            _write_json(staging / "source.json", {"recording_id": job.recording_id, "job": job.id})
            staging.replace(self.classifiers_dir / job.id)
            job = job.model_copy(
                update={
                    "state": "done",
                    "classifier_id": job.id,
                    "metrics": result.metrics,
                    "finished_at": _now(),
                }
            )
        except Exception as exc:
            shutil.rmtree(staging, ignore_errors=True)
            job = job.model_copy(
                update={
                    "state": "failed",
                    "error": f"{type(exc).__name__}: {exc}",
                    "finished_at": _now(),
                }
            )
        self.save_job(job)

    # classifiers
    def classifier(self, classifier_id: str) -> Any:
        from services.eeg.classifier import ErrPClassifier

        folder = self.classifiers_dir / classifier_id
        if not classifier_id.isalnum() or not folder.is_dir():
            raise HTTPException(404, f"no classifier {classifier_id!r}")
        with self._lock:
            if classifier_id not in self._classifiers:
                try:
                    self._classifiers[classifier_id] = ErrPClassifier.load(folder)
                except ValueError as exc:
                    raise HTTPException(409, f"classifier {classifier_id!r}: {exc}") from exc
            return self._classifiers[classifier_id]

    def classifier_public(self, classifier_id: str) -> ClassifierPublic:
        clf = self.classifier(classifier_id)
        source = self.classifiers_dir / classifier_id / "source.json"
        recording_id = json.loads(source.read_text())["recording_id"] if source.is_file() else None
        return ClassifierPublic(
            id=classifier_id,
            recording_id=recording_id,
            synthetic=clf.synthetic,
            ch_names=clf.ch_names,
            sfreq_in=clf.sfreq_in,
            epoch_shape=clf.epoch_shape,
            metrics=clf.metrics,
        )

    # live
    def decode(
        self, result: EpochResult, marker: ActionMarker | None, live: LiveSession
    ) -> Feedback:
        """Feedback for one epoch request of the live session ``live``."""
        common = {
            "onset": result.onset,
            "step": marker.step if marker else None,
            "session_id": marker.session_id if marker else None,
            "classifier_id": live.classifier_id,
            "synthetic": live.classifier.synthetic,
        }
        if not result.ok:
            return Feedback(status="rejected", reason=result.reason, **common)
        p_error = float(live.classifier.predict_proba(result.epoch)[0])
        return Feedback(
            status="ok",
            p_error=p_error,
            feedback="error" if p_error >= 0.5 else "correct",
            **common,
        )

    def broadcast(self, message: dict[str, Any]) -> None:
        """Send a message to every feedback websocket (thread-safe)."""
        if self.loop is None:
            return
        for queue in list(self.subscribers):
            self.loop.call_soon_threadsafe(queue.put_nowait, message)

    def set_live(self, session: LiveSession | None) -> None:
        with self._lock:
            previous, self.live = self.live, session
        if previous is not None:
            previous.close()

    def close(self) -> None:
        self.set_live(None)
        self.executor.shutdown(wait=False, cancel_futures=True)


def get_service(connection: HTTPConnection) -> EEGService:
    """The service state of the app handling this request."""
    return connection.app.state.service


ServiceDep = Annotated[EEGService, Depends(get_service)]


# ----------------------------------------------------------------------------- routes
recordings = APIRouter(prefix="/recordings", tags=["recordings"])


@recordings.post("", status_code=201, response_model=RecordingPublic)
async def upload_recording(
    request: Request,
    service: ServiceDep,
    filename: Annotated[str, Query(min_length=5, max_length=200)],
) -> Any:
    """Store a recording sent as the request body (the raw file bytes)."""
    suffix = Path(filename).suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise HTTPException(
            415, f"unsupported format {suffix!r}; use one of {', '.join(SUPPORTED_SUFFIXES)}"
        )
    limit = service.settings.max_upload_bytes
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise HTTPException(413, f"recording is {declared} bytes; the limit is {limit}")
    fd, tmp_name = tempfile.mkstemp(prefix=".upload-", suffix=suffix, dir=service.recordings_dir)
    tmp = Path(tmp_name)
    try:
        size = 0
        with os.fdopen(fd, "wb") as fh:
            async for chunk in request.stream():
                size += len(chunk)
                if size > limit:
                    raise HTTPException(413, f"recording exceeds the {limit}-byte limit")
                fh.write(chunk)
        if size == 0:
            raise HTTPException(422, "empty upload: send the file's bytes as the request body")
        try:
            raw = await asyncio.to_thread(read_recording, tmp)
        except RecordingError as exc:
            raise HTTPException(422, str(exc).replace(tmp.name, filename)) from exc
        sha = await asyncio.to_thread(file_sha256, tmp)
        meta_path = service.recordings_dir / f"{sha}.json"
        if meta_path.is_file():
            return JSONResponse(json.loads(meta_path.read_text()), status_code=200)
        events = action_events(raw)
        meta = RecordingPublic(
            id=sha,
            filename=Path(filename).name,
            format=suffix[1:],
            sha256=sha,
            size_bytes=size,
            sfreq=float(raw.info["sfreq"]),
            n_channels=len(raw.ch_names),
            duration_s=raw.n_times / raw.info["sfreq"],
            n_actions=len(events),
            n_errors=int(np.sum(events[:, 2] == 2)),
            synthetic=is_synthetic(raw),
            uploaded_at=_now(),
        )
        tmp.replace(service.recordings_dir / f"{sha}{suffix}")
        _write_json(meta_path, meta.model_dump())
        return meta
    finally:
        tmp.unlink(missing_ok=True)


@recordings.get("", response_model=list[RecordingPublic])
def list_recordings(service: ServiceDep) -> list[RecordingPublic]:
    """Every stored recording."""
    return [
        RecordingPublic.model_validate_json(p.read_text())
        for p in sorted(service.recordings_dir.glob("*.json"))
    ]


@recordings.get("/{recording_id}", response_model=RecordingPublic)
def get_recording(recording_id: str, service: ServiceDep) -> RecordingPublic:
    """One stored recording."""
    return service.recording(recording_id)


jobs = APIRouter(prefix="/jobs", tags=["jobs"])


@jobs.post("", status_code=202, response_model=JobPublic)
def start_job(body: JobCreate, service: ServiceDep) -> JobPublic:
    """Start calibration training on a stored recording, in the background."""
    service.recording(body.recording_id)
    if body.max_epochs > service.settings.max_training_epochs:
        raise HTTPException(
            422, f"max_epochs may be at most {service.settings.max_training_epochs}"
        )
    job = JobPublic(
        id=uuid.uuid4().hex[:16],
        recording_id=body.recording_id,
        seed=body.seed,
        max_epochs=body.max_epochs,
        state="queued",
        created_at=_now(),
    )
    service.save_job(job)
    service.executor.submit(service.run_job, job)
    return job


@jobs.get("", response_model=list[JobPublic])
def list_jobs(service: ServiceDep) -> list[JobPublic]:
    """Every job, oldest first."""
    found = [JobPublic.model_validate_json(p.read_text()) for p in service.jobs_dir.glob("*.json")]
    return sorted(found, key=lambda j: j.created_at)


@jobs.get("/{job_id}", response_model=JobPublic)
def get_job(job_id: str, service: ServiceDep) -> JobPublic:
    """One job's state."""
    return service.job(job_id)


classifiers = APIRouter(prefix="/classifiers", tags=["classifiers"])


@classifiers.get("", response_model=list[ClassifierPublic])
def list_classifiers(service: ServiceDep) -> list[ClassifierPublic]:
    """Trained classifiers with their calibration metrics."""
    return [
        service.classifier_public(p.name)
        for p in sorted(service.classifiers_dir.iterdir())
        if p.is_dir() and not p.name.startswith(".")
    ]


@classifiers.get("/{classifier_id}", response_model=ClassifierPublic)
def get_classifier(classifier_id: str, service: ServiceDep) -> ClassifierPublic:
    """One classifier."""
    return service.classifier_public(classifier_id)


@classifiers.post("/{classifier_id}/classify", response_model=Feedback)
def classify_epoch(classifier_id: str, body: EpochClassify, service: ServiceDep) -> Feedback:
    """Classify one preprocessed epoch; its shape, channels and rate must match."""
    clf = service.classifier(classifier_id)
    if body.ch_names != clf.ch_names:
        missing = [c for c in clf.ch_names if c not in body.ch_names]
        raise HTTPException(
            422,
            f"channels do not match the classifier's {len(clf.ch_names)} channels"
            + (f" (missing {', '.join(missing[:8])})" if missing else " (order differs)"),
        )
    if not np.isclose(body.sfreq, clf.params.sfreq_out):
        raise HTTPException(
            422, f"epoch rate {body.sfreq:g} Hz; the classifier takes {clf.params.sfreq_out:g} Hz"
        )
    rows = {len(row) for row in body.epoch}
    if len(body.epoch) != clf.epoch_shape[0] or rows != {clf.epoch_shape[1]}:
        raise HTTPException(
            422,
            f"epoch must be {clf.epoch_shape[0]} x {clf.epoch_shape[1]} (channels x times), "
            f"got {len(body.epoch)} rows of {sorted(rows)} samples",
        )
    X = np.asarray(body.epoch, dtype=np.float64)
    if not np.all(np.isfinite(X)):
        raise HTTPException(422, "epoch contains NaN or infinite values")
    p_error = float(clf.predict_proba(X)[0])
    return Feedback(
        status="ok",
        p_error=p_error,
        feedback="error" if p_error >= 0.5 else "correct",
        classifier_id=classifier_id,
        synthetic=clf.synthetic,
    )


live = APIRouter(prefix="/live", tags=["live"])


def _live_status(service: EEGService) -> LiveStatus:
    session = service.live
    if session is None:
        return LiveStatus(connected=False)
    ingest = session.ingest
    return LiveStatus(
        connected=not ingest.disconnected,
        source=session.source,
        classifier_id=session.classifier_id,
        stream_name=session.stream_name,
        marker_stream=session.marker_stream,
        n_samples=ingest.n_samples,
        latest_timestamp=ingest.latest_timestamp,
        issues=[
            {"kind": i.kind, "start": i.start, "end": i.end, "detail": i.detail}
            for i in ingest.issues[-100:]
        ],
    )


@live.post("", response_model=LiveStatus)
def connect_live(body: LiveConnect, service: ServiceDep) -> LiveStatus:
    """Connect an LSL EEG stream, checked against the classifier's channels and rate."""
    from services.eeg.lsl import LslEegIngest

    clf = service.classifier(body.classifier_id)
    try:
        source = LslEegIngest(
            body.stream_name,
            eeg_ch_names=clf.ch_names,
            params=clf.params,
            timeout=service.settings.lsl_timeout_s,
        )
    except (RuntimeError, ValueError) as exc:
        raise HTTPException(422, str(exc)) from exc
    try:
        clf.check_compatible(source.ingest.eeg_ch_names, source.ingest.sfreq)
    except ValueError as exc:
        source.close()
        raise HTTPException(422, f"stream {body.stream_name!r}: {exc}") from exc
    session = LiveSession(
        source.ingest, clf, body.classifier_id, "lsl", stream_name=body.stream_name, lsl=source
    )
    if body.marker_stream is not None:
        try:
            session.follow_markers(service, body.marker_stream, service.settings.lsl_timeout_s)
        except RuntimeError as exc:
            session.close()
            raise HTTPException(422, str(exc)) from exc
    service.set_live(session)
    return _live_status(service)


@live.get("", response_model=LiveStatus)
def live_status(service: ServiceDep) -> LiveStatus:
    """The live source and the problems detected in it."""
    if service.live is not None:
        service.live.ingest.check_stale()
    return _live_status(service)


@live.delete("", response_model=LiveStatus)
def disconnect_live(service: ServiceDep) -> LiveStatus:
    """Disconnect the live source."""
    service.set_live(None)
    return _live_status(service)


@live.post("/markers", response_model=Feedback)
def classify_marker(marker: ActionMarker, service: ServiceDep) -> Feedback:
    """Classify the epoch after an action marker (LSL clock) from the live stream."""
    session = service.live
    if session is None:
        raise HTTPException(409, "no live EEG source: POST /live or open WS /live/ingest first")
    result = session.ingest.wait_epoch(marker.timestamp, timeout_s=service.settings.epoch_wait_s)
    feedback = service.decode(result, marker, session)
    service.broadcast(feedback.model_dump())
    return feedback


def _origin_allowed(websocket: WebSocket, settings: EEGSettings) -> bool:
    """Same-host origins, configured origins, and clients that send no Origin (not browsers)."""
    origin = websocket.headers.get("origin")
    if origin is None or origin in settings.allowed_origins:
        return True
    host = websocket.headers.get("host", "")
    return bool(host) and urlsplit(origin).netloc.lower() == host.lower()


@live.websocket("/feedback")
async def feedback_socket(websocket: WebSocket) -> None:
    """Every decoded feedback, as JSON messages (:class:`Feedback`)."""
    service: EEGService = websocket.app.state.service
    if not _origin_allowed(websocket, service.settings):
        await websocket.close(code=4403, reason="origin not allowed")
        return
    await websocket.accept()
    queue: asyncio.Queue[dict[str, Any]] = asyncio.Queue(maxsize=1000)
    service.subscribers.add(queue)
    try:
        receiver = asyncio.create_task(websocket.receive_text())
        while True:
            getter = asyncio.create_task(queue.get())
            done, _ = await asyncio.wait({getter, receiver}, return_when=asyncio.FIRST_COMPLETED)
            if receiver in done:
                getter.cancel()
                break
            await websocket.send_json(getter.result())
    except WebSocketDisconnect:
        pass
    finally:
        service.subscribers.discard(queue)
        with suppress(Exception):
            receiver.cancel()


@live.websocket("/ingest")
async def ingest_socket(
    websocket: WebSocket, classifier_id: Annotated[str, Query(max_length=64)]
) -> None:
    """Sample chunks from a device without LSL.

    The first message is ``{"ch_names": [...], "sfreq": 2048}``; then each message is
    ``{"first_timestamp": t, "samples": [[...], ...]}`` (n_times x n_channels, volts,
    LSL clock). Each message is answered ``{"ok": true, "n_samples": N}`` or
    ``{"ok": false, "error": "..."}``; a bad header closes the socket with code 4422.
    """
    service: EEGService = websocket.app.state.service
    if not _origin_allowed(websocket, service.settings):
        await websocket.close(code=4403, reason="origin not allowed")
        return
    try:
        clf = service.classifier(classifier_id)
    except HTTPException as exc:
        await websocket.close(code=4404, reason=str(exc.detail))
        return
    await websocket.accept()
    header = await websocket.receive_json()
    try:
        ch_names = [str(c) for c in header["ch_names"]]
        sfreq = float(header["sfreq"])
        ingest = LiveIngest(ch_names, sfreq, eeg_ch_names=clf.ch_names, params=clf.params)
        clf.check_compatible(ingest.eeg_ch_names, sfreq)
    except (KeyError, TypeError, ValueError) as exc:
        await websocket.send_json({"ok": False, "error": f"bad header: {exc}"})
        await websocket.close(code=4422)
        return
    session = LiveSession(ingest, clf, classifier_id, "websocket")
    service.set_live(session)
    await websocket.send_json({"ok": True, "n_samples": 0})
    try:
        while True:
            message = await websocket.receive_json()
            try:
                samples = np.asarray(message["samples"], dtype=np.float64)
                ingest.push_chunk(samples, first_timestamp=float(message["first_timestamp"]))
            except (KeyError, TypeError, ValueError) as exc:
                await websocket.send_json({"ok": False, "error": str(exc)})
                continue
            await websocket.send_json({"ok": True, "n_samples": ingest.n_samples})
    except WebSocketDisconnect:
        pass
    finally:
        ingest.mark_disconnected("websocket closed")


# -------------------------------------------------------------------------------- app
def create_app(settings: EEGSettings | None = None) -> FastAPI:
    """Build the EEG service; ``settings`` default to the environment's ``BGRL_EEG_*``."""
    settings = settings if settings is not None else EEGSettings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        service = EEGService(settings)
        service.loop = asyncio.get_running_loop()
        app.state.service = service
        try:
            yield
        finally:
            service.close()

    app = FastAPI(
        title="BrainNav EEG service",
        summary="Recordings, ErrP calibration, classifiers and live decoding.",
        version="0.1.0",
        lifespan=lifespan,
        max_body_size=settings.max_upload_bytes,
    )
    app.state.settings = settings

    @app.get("/health", tags=["service"])
    def health() -> dict[str, Any]:
        return {"status": "ok", "service": "eeg"}

    for router in (recordings, jobs, classifiers, live):
        app.include_router(router)
    return app


app = create_app()
