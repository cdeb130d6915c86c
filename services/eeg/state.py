"""The state of one EEG service instance: its stores, job runner and live session."""

from __future__ import annotations

import asyncio
import logging
import math
import shutil
import threading
from pathlib import Path

from services.core.artifacts import ArtifactStore
from services.core.errors import ConflictError, NotFoundError
from services.eeg.errors import NoLiveSourceError
from services.eeg.jobs import JobRunner
from services.eeg.live_recording import (
    INDEX_FILE,
    LiveRecorder,
    RecordingLogError,
    read_log,
    write_bdf_from_log,
)
from services.eeg.live_session import FeedbackHub, LiveSession
from services.eeg.schemas import LiveRecordingPublic, RecordingPublic
from services.eeg.settings import EEGSettings
from services.eeg.store import ClassifierStore, JobStore, RecordingStore
from services.eeg.virtual_subject import STIM_CHANNEL

logger = logging.getLogger(__name__)


class EEGService:
    """Everything the routes of one app share; created at start-up, closed at shutdown."""

    def __init__(self, settings: EEGSettings, loop: asyncio.AbstractEventLoop) -> None:
        self.settings = settings
        root = settings.eeg_dir
        self.incoming = ArtifactStore(root)
        self.recordings = RecordingStore(root / "recordings", self.incoming)
        self.classifiers = ClassifierStore(root / "classifiers")
        self.jobs = JobStore(root / "jobs")
        self.runner = JobRunner(self.jobs, self.recordings, self.classifiers)
        self.hub = FeedbackHub(loop)
        self._live_lock = threading.Lock()
        self._live: LiveSession | None = None
        self.live_recordings = root / "live_recordings"
        self._recorder: LiveRecorder | None = None

    @property
    def live(self) -> LiveSession | None:
        """The current live session (possibly disconnected), or None."""
        return self._live

    def set_live(self, session: LiveSession | None, reason: str) -> None:
        """Make ``session`` the live session; the previous one is closed with ``reason``."""
        with self._live_lock:
            previous, self._live = self._live, session
            recorder = self._recorder
            if recorder is not None and previous is not None:
                self._detach(recorder, previous)
            if recorder is not None and session is not None:
                self._attach(recorder, session)
        if previous is not None:
            logger.info("closing the %s live source: %s", previous.source, reason)
            previous.close(reason)

    # ---------------------------------------------------------- live recording
    @staticmethod
    def _attach(recorder: LiveRecorder, session: LiveSession) -> None:
        """Record ``session``'s samples and markers, if its stream matches the recording."""
        ingest = session.ingest
        if ingest.stream_ch_names != recorder.ch_names or not math.isclose(
            ingest.sfreq, recorder.sfreq
        ):
            recorder.error = (
                "the new live source has other channels or another rate: not recorded "
                "(stop this recording and start another)"
            )
            logger.warning("live recording %s: %s", recorder.name, recorder.error)
            return
        recorder.error = None
        ingest.add_listener(recorder.add_samples)
        session.add_marker_listener(recorder.add_marker)

    @staticmethod
    def _detach(recorder: LiveRecorder, session: LiveSession) -> None:
        session.ingest.remove_listener(recorder.add_samples)
        session.remove_marker_listener(recorder.add_marker)

    def _recording_folder(self, name: str) -> Path:
        return self.live_recordings / name

    def start_recording(self, name: str) -> LiveRecordingPublic:
        """Start (or continue, after a crash) recording the live stream and its markers."""
        with self._live_lock:
            if self._recorder is not None:
                raise ConflictError(
                    f"already recording {self._recorder.name!r}: DELETE /live/recording first",
                    field="name",
                )
            session = self._live
            if session is None or session.closed:
                raise NoLiveSourceError(
                    "no live EEG source to record: POST /live or open WS /live/ingest first"
                )
            try:
                recorder = LiveRecorder(
                    self._recording_folder(name),
                    name=name,
                    ch_names=session.ingest.stream_ch_names,
                    sfreq=session.ingest.sfreq,
                    synthetic=session.synthetic,
                )
            except RecordingLogError as exc:
                raise ConflictError(str(exc), field="name") from None
            self._recorder = recorder
            self._attach(recorder, session)
        logger.info("live recording %s %s", name, "continued" if recorder.resumed else "started")
        return self.recording_status(recorder)

    @staticmethod
    def recording_status(recorder: LiveRecorder) -> LiveRecordingPublic:
        return LiveRecordingPublic(
            name=recorder.name,
            started_at=recorder.started_at,
            resumed=recorder.resumed,
            n_channels=len(recorder.ch_names),
            sfreq=recorder.sfreq,
            n_samples=round(recorder.duration_s() * recorder.sfreq),
            duration_s=recorder.duration_s(),
            n_markers=recorder.n_markers,
            synthetic=recorder.synthetic,
            error=recorder.error,
        )

    @property
    def recorder(self) -> LiveRecorder | None:
        """The live recording in progress, or None."""
        return self._recorder

    def unfinished_recordings(self) -> list[str]:
        """Names of recording folders not finalised (interrupted), except the current one."""
        if not self.live_recordings.is_dir():
            return []
        current = self._recorder.name if self._recorder is not None else None
        return sorted(
            p.name
            for p in self.live_recordings.iterdir()
            if (p / INDEX_FILE).is_file() and p.name != current
        )

    def stop_recording(self, name: str | None = None) -> RecordingPublic:
        """Stop the live recording and store it as a BDF recording.

        With ``name`` and no recording in progress, finalise that interrupted recording
        (everything up to its last flushed block). The folder is removed once the BDF is
        stored; if storing fails it stays, so nothing is lost.
        """
        with self._live_lock:
            recorder = self._recorder
            if recorder is not None and name is not None and name != recorder.name:
                raise ConflictError(
                    f"recording {recorder.name!r} is in progress, not {name!r}", field="name"
                )
            if recorder is not None:
                self._recorder = None
                if self._live is not None:
                    self._detach(recorder, self._live)
        if recorder is not None:
            recorder.close()
            name = recorder.name
        if name is None:
            raise ConflictError("no live recording in progress", field="name")
        folder = self._recording_folder(name)
        if not (folder / INDEX_FILE).is_file():
            raise NotFoundError(f"no live recording {name!r}", field="name")
        try:
            log = read_log(folder)
            finalised = write_bdf_from_log(log, folder / f"{name}.bdf")
        except (RecordingLogError, ValueError) as exc:
            raise ConflictError(f"recording {name!r} cannot be finalised: {exc}") from None
        notes = []
        if len(log.runs) > 1:
            notes.append(f"the stream had {len(log.runs) - 1} gap(s); samples are concatenated")
        if finalised.markers_outside:
            notes.append(f"{finalised.markers_outside} marker(s) fell outside the recorded data")
        eeg = [ch for ch in log.ch_names if ch != STIM_CHANNEL]
        meta = self.recordings.add_bdf(
            finalised.path, filename=f"{name}.bdf", ch_names=eeg, notes=notes
        )
        shutil.rmtree(folder, ignore_errors=True)
        logger.info("live recording %s stored as %s", name, meta.id[:12])
        return meta

    def close(self) -> None:
        """Flush a live recording, release the live source and stop the job runner."""
        try:
            recorder, self._recorder = self._recorder, None
            if recorder is not None:
                recorder.close()  # the folder stays: continue or finalise it after a restart
            self.set_live(None, "the EEG service is stopping")
        finally:
            self.runner.close()
