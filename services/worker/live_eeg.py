"""The EEG side of a live session: the classifier installed in the EEG service, the source
feeding it (virtual subject accelerated or real time, or a headset's LSL stream), and one
decision per marker through ``POST /live/markers``. A calibration binds no classifier: the
EEG service records the stream and every marker (``POST /live/recording``, written to disk
as they arrive) and stores the recording as a BDF when the session ends.

The virtual subject runs in the runner's process and pushes its samples to ``WS
/live/ingest``: accelerated, on a virtual clock advanced only as far as each epoch needs;
in real time, from a thread at wall-clock pace (``LAG_S`` behind, so a marker arriving a
few ms after its action is never late). A headset is connected with ``POST /live``.
If the EEG service restarts, the source re-attaches (new ingest, settling time) and the
epoch in flight is lost: its decision is recorded as rejected with that reason.
"""

from __future__ import annotations

import logging
import math
import shutil
import threading
import time
from collections.abc import Callable
from typing import Any

from mne_lsl.lsl import local_clock
from sqlalchemy import select
from websockets.exceptions import WebSocketException

from services.core.db.models import Artifact, Classifier, Job
from services.core.markers import ActionMarker
from services.eeg.service.settings import EEGSettings
from services.eeg.service.store import ClassifierStore
from services.eeg.virtual.ingest import VirtualIngestClient
from services.eeg.virtual.source import VirtualEEGSource
from services.worker.live_services import (
    OutcomeUnknownError,
    ServiceCallError,
    ServiceClient,
    retry_while_down,
)
from services.worker.runtime import JobConfigError, Runtime

logger = logging.getLogger(__name__)

EPOCH_END_S = 0.8
"""End of the epoch after a marker (the paper's [0, 0.8] s)."""
WARMUP_S = 3.0
"""Samples pushed after (re)connecting before the next marker (the filter settles in 1 s)."""
LAG_S = 0.2
"""The real-time virtual subject generates this far behind the clock."""
FEED_EVERY_S = 0.02
RECORDING_MARGIN_S = 2.0
"""EEG recorded after the last marker of a calibration before the recording is stored."""


def install_classifier(runtime: Runtime, classifier_id: int) -> str:
    """Make the platform classifier ``classifier_id`` available to the EEG service; returns
    its id there (the calibration job's id). The EEG service reads classifiers from its data
    folder, which the worker shares on one host (``bgrl up``)."""
    with runtime.sessions() as session:
        classifier = session.get(Classifier, classifier_id)
        if classifier is None:
            raise JobConfigError(f"classifier_id: no classifier {classifier_id}")
        job = session.get(Job, classifier.job_id) if classifier.job_id else None
        files = dict((job.result or {}).get("artifacts", {})) if job is not None else {}
        relpaths = {
            name: session.scalar(select(Artifact.relpath).where(Artifact.id == artifact_id))
            for name, artifact_id in files.items()
        }
    if job is None or "classifier.json" not in relpaths:
        raise JobConfigError(f"classifier_id: classifier {classifier_id} has no stored files")
    store = ClassifierStore(EEGSettings(data_dir=runtime.settings.data_dir).eeg_dir / "classifiers")
    eeg_id = job.id
    if (store.folder / eeg_id).is_dir():
        return eeg_id
    staging = store.staging(eeg_id)
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    for name, relpath in relpaths.items():
        if relpath is not None and (name.startswith("model") or name == "classifier.json"):
            shutil.copyfile(runtime.store.path(relpath), staging / name)
    store.publish(eeg_id, f"platform-classifier-{classifier_id}")
    return eeg_id


def _attach_may_succeed_later(exc: Exception) -> bool:
    """Whether attaching to the EEG service is worth another try after ``exc``: not after a
    refusal of the request itself (400, 404, 422), nor after a call whose outcome is unknown
    (never repeated blindly)."""
    if isinstance(exc, ServiceCallError):
        return exc.status_code not in (400, 404, 422)
    if isinstance(exc, OutcomeUnknownError):
        return False
    return isinstance(exc, OSError | RuntimeError | WebSocketException)


class EegDecoder:
    """Feeds the EEG service and asks it for the decision on each marker."""

    def __init__(
        self,
        eeg: ServiceClient,
        classifier_id: str | None,
        *,
        source: VirtualEEGSource | None,
        accelerated: bool,
        stream_name: str | None,
        retry_s: float,
        period_s: float,
        recording: str | None = None,
        channel_map: dict[str, str] | None = None,
    ) -> None:
        self.eeg = eeg
        self.channel_map = channel_map
        """The rig's {device name: standard name} for the LSL stream (None: standard)."""
        self.recording = recording
        """Name of the EEG service's live recording of this source (calibration), if any."""
        self.classifier_id = classifier_id
        self.source = source
        self.accelerated = accelerated
        self.stream_name = stream_name
        self.retry_s = retry_s
        self.period_s = period_s
        self._ingest: VirtualIngestClient | None = None
        self._lock = threading.Lock()
        self._feeder: threading.Thread | None = None
        self._stop = threading.Event()
        self._reconnect_needed = False
        self.epoch_pushed_ts: dict[float, float] = {}
        self.virtual_now = source.next_timestamp if source is not None else 0.0
        self.reconnects = 0

    # ------------------------------------------------------------------ attach
    def attach(self) -> None:
        """Connect the source to the EEG service (retrying while it is down: its calls are
        idempotent, the ingest socket is opened anew)."""
        retry_while_down(
            self._attach_once,
            what=f"the EEG service at {self.eeg.base_url} cannot be attached",
            retry_s=self.retry_s,
            retryable=_attach_may_succeed_later,
        )

    def _attach_once(self) -> None:
        if self.source is None:
            assert self.stream_name is not None
            attach: dict[str, Any] = {
                "classifier_id": self.classifier_id,
                "stream_name": self.stream_name,
            }
            if self.channel_map:
                attach["channel_map"] = self.channel_map
            self.eeg.call("POST", "/live", json=attach, idempotent=True)  # replaces the source
            self._start_recording()
            time.sleep(WARMUP_S)  # the first marker must find data (and a settled filter)
            return
        with self._lock:
            if self._ingest is not None:
                self._ingest.close()
            self._ingest = VirtualIngestClient.connect(
                self.source, self.eeg.base_url, self.classifier_id, headers=self.eeg.headers
            )
            if self.accelerated:
                self.virtual_now = max(self.virtual_now, self.source.next_timestamp) + WARMUP_S
                self._ingest.push_until(self.virtual_now)
        self._start_recording()
        if not self.accelerated and self._feeder is None:
            self._feeder = threading.Thread(target=self._feed, name="virtual-eeg", daemon=True)
            self._feeder.start()
        if not self.accelerated:
            time.sleep(WARMUP_S)

    def _start_recording(self) -> None:
        """Start (or, after a crash of the EEG service, continue) the live recording."""
        if self.recording is None:
            return
        try:
            self.eeg.call(  # sent again: 409, and the recording goes on
                "POST", "/live/recording", json={"name": self.recording}, idempotent=True
            )
        except ServiceCallError as exc:
            if exc.status_code != 409:
                raise
            status = self.eeg.call("GET", "/live")
            current = (status.get("recording") or {}).get("name")
            if current != self.recording:  # another recording runs: never mix two sessions
                raise
            logger.info("live recording %s goes on", self.recording)

    def stop_recording(self, last_marker_ts: float | None) -> dict[str, Any]:
        """Record :data:`RECORDING_MARGIN_S` after the last marker (None: no marker), then
        have the EEG service store the recording (BDF, sha256); returns its
        ``RecordingPublic``."""
        assert self.recording is not None
        end = (last_marker_ts if last_marker_ts is not None else -math.inf) + RECORDING_MARGIN_S
        if last_marker_ts is None:
            pass
        elif self.source is not None and self.accelerated:
            with self._lock:
                if self._ingest is not None:
                    self._ingest.push_until(end)
        elif self.source is not None:
            while self.source.next_timestamp < end and not self._reconnect_needed:
                time.sleep(FEED_EVERY_S)
        else:  # a headset: its samples arrive in real time, a little late
            time.sleep(max(0.0, end + LAG_S - local_clock()))
        return self.eeg.call("DELETE", "/live/recording", params={"name": self.recording})

    def _feed(self) -> None:
        """Real time: push the virtual subject's samples up to ``now - LAG_S``."""
        while not self._stop.wait(FEED_EVERY_S):
            with self._lock:
                ingest = self._ingest
                if ingest is None or self._reconnect_needed:
                    continue
                try:
                    ingest.push_until(local_clock() - LAG_S)
                except Exception as exc:  # the EEG service went away: the runner re-attaches
                    logger.warning("virtual EEG feed stopped: %s", exc)
                    self._reconnect_needed = True
                    continue
                now = local_clock()
                for onset in [t for t in self.epoch_pushed_ts if self.epoch_pushed_ts[t] == 0.0]:
                    if ingest.source.next_timestamp >= onset + EPOCH_END_S:
                        self.epoch_pushed_ts[onset] = now

    # ------------------------------------------------------------------ markers
    def next_eeg_timestamp(self, marker_ts: float) -> float:
        """The marker's time on the EEG clock: the virtual clock when accelerated."""
        if not self.accelerated:
            return marker_ts
        self.virtual_now += self.period_s
        return self.virtual_now

    def decide(self, marker: ActionMarker) -> tuple[dict[str, Any], float | None, float]:
        """The EEG service's decision on ``marker`` (on the EEG clock), when its epoch was
        complete there and when the decision arrived (runner clock). A lost connection
        re-attaches and rejects the epoch."""
        try:
            epoch_end = self._feed_marker(marker)
            feedback = self.eeg.call(  # a decision is computed again from the same epoch
                "POST", "/live/markers", json=marker.model_dump(mode="json"), idempotent=True
            )
            decided = local_clock()
        except ServiceCallError as exc:
            if exc.status_code != 409:  # 409: no live source (the EEG service restarted)
                raise
            return self._lost(f"EEG live source gone ({exc.detail})"), None, local_clock()
        except (OSError, RuntimeError, WebSocketException) as exc:
            lost = self._lost(f"EEG ingest failed ({type(exc).__name__}: {exc})")
            return lost, None, local_clock()
        if not self.accelerated and self.source is not None:
            with self._lock:
                epoch_end = self.epoch_pushed_ts.pop(marker.timestamp, 0.0) or None
        return feedback, epoch_end, decided

    def _feed_marker(self, marker: ActionMarker) -> float | None:
        if self.source is None:
            return None
        with self._lock:
            if self._reconnect_needed or self._ingest is None:
                raise RuntimeError("the EEG ingest was disconnected")
            self._ingest.add_marker(marker)
            if not self.accelerated:
                self.epoch_pushed_ts[marker.timestamp] = 0.0
                return None
            self._ingest.push_until(marker.timestamp + EPOCH_END_S + 2.0 / self.source.sfreq)
            return local_clock()

    def _lost(self, reason: str) -> dict[str, Any]:
        logger.warning("epoch lost: %s", reason)
        self.reconnects += 1
        with self._lock:
            self._reconnect_needed = False
            self.epoch_pushed_ts.clear()
        self.attach()
        return {"status": "rejected", "reason": f"lost: {reason}", "p_error": None}

    def close(self, on_error: Callable[[Exception], None] | None = None) -> None:
        self._stop.set()
        if self._feeder is not None:
            self._feeder.join(timeout=5)
        with self._lock:
            if self._ingest is not None:
                try:
                    self._ingest.close()
                except Exception as exc:
                    if on_error is not None:
                        on_error(exc)
                self._ingest = None
