"""The live session (one EEG source bound to one classifier) and the feedback broadcast.

A :class:`LiveSession` owns its source: an LSL inlet (:class:`~services.eeg.live.lsl.LslEegIngest`)
or the chunks of a ``WS /live/ingest`` connection, and optionally a thread that classifies
every marker of the sim's LSL marker stream. A failure in a background thread is logged and
kept in :attr:`LiveSession.error`, so ``GET /live`` reports it instead of "connected".
:class:`FeedbackHub` hands every decoded feedback to the ``WS /live/feedback`` clients.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
from collections.abc import Callable
from contextlib import suppress
from typing import Any, Literal, Protocol

from services.core.feedback import is_error
from services.core.markers import ActionMarker
from services.eeg.decoding.classifier import ErrPClassifier
from services.eeg.live.ingest import EpochResult, LiveIngest
from services.eeg.service.schemas import Feedback, LiveStatus, StreamIssuePublic

logger = logging.getLogger(__name__)

SUBSCRIBER_QUEUE = 1000
"""Feedback messages buffered per websocket client; a client that lags further loses the
oldest ones."""
JOIN_TIMEOUT_S = 5.0
NO_CLASSIFIER = "no classifier bound to the live source (markers are only recorded)"


class EegSource(Protocol):
    """An EEG source that owns a :class:`LiveIngest` (e.g. an LSL inlet)."""

    ingest: LiveIngest

    @property
    def error(self) -> str | None: ...

    def close(self) -> None: ...


class MarkerSource(Protocol):
    """A source of action markers (e.g. :class:`~services.eeg.live.lsl.MarkerInlet`)."""

    def pull(self, timeout: float = 0.0) -> Any: ...

    def close(self) -> None: ...


class FeedbackHub:
    """Fans feedback messages out to every subscribed websocket (thread-safe)."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._lock = threading.Lock()
        self._queues: set[asyncio.Queue[dict[str, Any]]] = set()

    def subscribe(self) -> asyncio.Queue[dict[str, Any]]:
        """A new queue receiving every message from now on (call from the event loop)."""
        queue: asyncio.Queue[dict[str, Any]] = asyncio.Queue(maxsize=SUBSCRIBER_QUEUE)
        with self._lock:
            self._queues.add(queue)
        return queue

    def unsubscribe(self, queue: asyncio.Queue[dict[str, Any]]) -> None:
        with self._lock:
            self._queues.discard(queue)

    @staticmethod
    def _put(queue: asyncio.Queue[dict[str, Any]], message: dict[str, Any]) -> None:
        if queue.full():
            queue.get_nowait()  # the client lags: drop its oldest message
        queue.put_nowait(message)

    def broadcast(self, message: dict[str, Any]) -> None:
        """Send ``message`` to every subscriber (from any thread)."""
        with self._lock:
            queues = list(self._queues)
        for queue in queues:
            with suppress(RuntimeError):  # the loop is closed: the service is stopping
                self._loop.call_soon_threadsafe(self._put, queue, message)


class LiveSession:
    """The live source bound to one classifier (or none: recording only); :meth:`close`
    releases everything."""

    def __init__(
        self,
        ingest: LiveIngest,
        classifier: ErrPClassifier | None,
        classifier_id: str | None,
        source: Literal["lsl", "websocket"],
        *,
        stream_name: str | None = None,
        eeg_source: EegSource | None = None,
        synthetic: bool = False,
    ) -> None:
        self.ingest = ingest
        self.synthetic = synthetic
        """The source says its data are generated (a virtual subject)."""
        self.classifier = classifier
        self.classifier_id = classifier_id
        self.source = source
        self.stream_name = stream_name
        self.eeg_source = eeg_source
        self.marker_stream: str | None = None
        self._failure: str | None = None
        self._stop = threading.Event()
        self._marker_thread: threading.Thread | None = None
        self._on_close: list[Callable[[], None]] = []
        self._marker_listeners: list[Callable[[ActionMarker], None]] = []
        self.close_reason: str | None = None

    @property
    def closed(self) -> bool:
        return self._stop.is_set()

    @property
    def error(self) -> str | None:
        """Why the source stopped working (a background failure), or None."""
        if self._failure is not None:
            return self._failure
        return self.eeg_source.error if self.eeg_source is not None else None

    def fail(self, message: str) -> None:
        """Record a background failure: the status shows it and the source counts as gone."""
        if self._failure is None:
            self._failure = message
        self.ingest.mark_disconnected(message)

    def decode(self, result: EpochResult, marker: ActionMarker | None) -> Feedback:
        """Feedback for one epoch request (classified if the epoch is clean)."""
        common = {
            "onset": result.onset,
            "step": marker.step if marker else None,
            "session_id": marker.session_id if marker else None,
            "classifier_id": self.classifier_id,
            "synthetic": self.classifier.synthetic if self.classifier else self.synthetic,
        }
        if self.classifier is None:
            return Feedback(status="rejected", reason=NO_CLASSIFIER, **common)
        if not result.ok:
            return Feedback(status="rejected", reason=result.reason, **common)
        p_error, log_likelihood_ratio = self.classifier.decode_epoch(result.epoch)
        return Feedback(
            status="ok",
            p_error=p_error,
            log_likelihood_ratio=log_likelihood_ratio,
            feedback="error" if is_error(p_error) else "correct",
            **common,
        )

    def classify_marker(self, marker: ActionMarker, wait_s: float) -> Feedback:
        """Wait up to ``wait_s`` for the epoch after ``marker`` and decode it."""
        for listener in list(self._marker_listeners):
            listener(marker)
        if self.classifier is None:
            return self.decode(EpochResult(marker.timestamp, "rejected"), marker)
        result = self.ingest.wait_epoch(marker.timestamp, timeout_s=wait_s, stop=self._stop)
        return self.decode(result, marker)

    def follow_markers(
        self, inlet: MarkerSource, name: str, hub: FeedbackHub, wait_s: float
    ) -> None:
        """Classify every marker ``inlet`` receives in a thread, broadcasting the feedback.

        The session owns ``inlet`` from now on (it is closed with the session). A malformed
        marker is logged and recorded as a ``bad_marker`` issue; any other failure stops
        the thread and is reported by :attr:`error`.
        """
        self.marker_stream = name

        def run() -> None:
            try:
                while not self._stop.is_set():
                    pulled = inlet.pull(timeout=0.1)
                    for rejected in pulled.rejected:
                        logger.warning("skipping a malformed marker: %s", rejected.reason)
                        self.ingest.report_bad_marker(rejected.timestamp, rejected.reason)
                    for marker in pulled.markers:
                        feedback = self.classify_marker(marker, wait_s)
                        hub.broadcast(feedback.model_dump(mode="json"))
            except Exception as exc:
                logger.exception("marker stream %r stopped", name)
                self.fail(f"marker stream {name!r} failed: {type(exc).__name__}: {exc}")
            finally:
                inlet.close()

        self._marker_thread = threading.Thread(target=run, name="lsl-markers", daemon=True)
        self._marker_thread.start()

    def add_marker_listener(self, listener: Callable[[ActionMarker], None]) -> None:
        """Call ``listener(marker)`` with every marker classified (e.g. a live recorder)."""
        self._marker_listeners.append(listener)

    def remove_marker_listener(self, listener: Callable[[ActionMarker], None]) -> None:
        with suppress(ValueError):
            self._marker_listeners.remove(listener)

    def on_close(self, callback: Callable[[], None]) -> None:
        """Call ``callback`` (once) when the session is closed."""
        self._on_close.append(callback)
        if self.closed:
            callback()

    def close(self, reason: str = "live source disconnected") -> None:
        """Stop the marker thread and release the source (idempotent)."""
        if self._stop.is_set():
            return
        self.close_reason = reason
        self._stop.set()
        try:
            if self._marker_thread is not None:
                self._marker_thread.join(timeout=JOIN_TIMEOUT_S)
                if self._marker_thread.is_alive():
                    logger.warning("marker thread did not stop within %g s", JOIN_TIMEOUT_S)
        finally:
            if self.eeg_source is not None:
                self.eeg_source.close()
            else:
                self.ingest.mark_disconnected(reason)
            for callback in self._on_close:
                callback()

    def status(self) -> LiveStatus:
        """The session as ``GET /live`` shows it."""
        if not self.closed:
            self.ingest.check_stale()
        error = self.error
        return LiveStatus(
            connected=not self.closed and not self.ingest.disconnected and error is None,
            source=self.source,
            classifier_id=self.classifier_id,
            stream_name=self.stream_name,
            marker_stream=self.marker_stream,
            n_samples=self.ingest.n_samples,
            latest_timestamp=self.ingest.latest_timestamp,
            error=error,
            issues=[
                StreamIssuePublic(
                    kind=issue.kind,
                    start=issue.start,
                    end=issue.end if math.isfinite(issue.end) else None,
                    detail=issue.detail,
                )
                for issue in self.ingest.issues
            ],
            issues_dropped=self.ingest.issues_dropped,
        )
