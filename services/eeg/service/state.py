"""The state of one EEG service instance: its stores, job runner and live session."""

from __future__ import annotations

import asyncio
import json
import logging
import math
import shutil
import threading
from pathlib import Path

from services.core.artifacts import ArtifactStore
from services.core.errors import ConflictError, NotFoundError
from services.core.files import write_json_atomic
from services.eeg.live.recording import (
    INDEX_FILE,
    STORED_FILE,
    LiveRecorder,
    RecordingLogError,
    read_log,
    write_bdf_from_log,
)
from services.eeg.recordings.conventions import STIM_CHANNEL
from services.eeg.recordings.io import file_sha256
from services.eeg.service.errors import NoLiveSourceError, RecordingNotFoundError
from services.eeg.service.jobs import JobRunner
from services.eeg.service.live_session import FeedbackHub, LiveSession
from services.eeg.service.schemas import LiveRecordingPublic, RecordingPublic
from services.eeg.service.settings import EEGSettings
from services.eeg.service.store import ClassifierStore, JobStore, RecordingStore

logger = logging.getLogger(__name__)


class EEGService:
    """Everything the routes of one app share; created at start-up, closed at shutdown."""

    def __init__(self, settings: EEGSettings, loop: asyncio.AbstractEventLoop) -> None:
        self.settings = settings
        root = settings.eeg_dir
        self.incoming = ArtifactStore(root)
        self.incoming.remove_abandoned_parts()  # uploads of a killed service
        self.recordings = RecordingStore(root / "recordings", self.incoming)
        self.classifiers = ClassifierStore(root / "classifiers")
        self.jobs = JobStore(root / "jobs")
        self.runner = JobRunner(self.jobs, self.recordings, self.classifiers)
        self.hub = FeedbackHub(loop)
        self._live_lock = threading.Lock()
        self._live: LiveSession | None = None
        self.live_recordings = root / "live_recordings"
        self._recorder: LiveRecorder | None = None
        self.remove_stored_folders()

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

    def _stored_as(self, folder: Path) -> RecordingPublic | None:
        """The stored recording ``folder`` was finalised to, if the store has it (a crash
        came between storing it and removing the folder), else None."""
        try:
            sha = json.loads((folder / STORED_FILE).read_text())["sha256"]
            return self.recordings.get(sha)
        except (OSError, ValueError, KeyError, TypeError, RecordingNotFoundError):
            return None

    @staticmethod
    def _remove_folder(folder: Path) -> None:
        """Remove a stored recording's folder, its :data:`STORED_FILE` last: a crash on
        the way leaves a folder that still says it was stored, removed at the next chance."""
        for path in folder.iterdir():
            if path.is_dir():
                shutil.rmtree(path)
            elif path.name != STORED_FILE:
                path.unlink()
        (folder / STORED_FILE).unlink(missing_ok=True)
        folder.rmdir()

    def _remove_if_stored(self, folder: Path) -> RecordingPublic | None:
        """Remove ``folder`` if its recording is already stored; returns that recording."""
        meta = self._stored_as(folder)
        if meta is not None:
            self._remove_folder(folder)
            logger.info(
                "live recording %s was stored as %s: folder removed", folder.name, meta.id[:12]
            )
        return meta

    def remove_stored_folders(self) -> list[str]:
        """Remove the folders of live recordings already stored, left by a crash between
        storing and removing (and empty ones); returns their names. Called at start-up."""
        if not self.live_recordings.is_dir():
            return []
        current = self._recorder.name if self._recorder is not None else None
        removed = []
        for folder in sorted(p for p in self.live_recordings.iterdir() if p.is_dir()):
            if folder.name == current:
                continue
            try:
                if not any(folder.iterdir()):
                    folder.rmdir()
                    removed.append(folder.name)
                elif self._remove_if_stored(folder) is not None:
                    removed.append(folder.name)
            except OSError as exc:  # the service still starts; the next start tries again
                logger.warning("live recording folder %s not removed: %s", folder.name, exc)
        return removed

    def start_recording(self, name: str) -> LiveRecordingPublic:
        """Start (or continue, after a crash) recording the live stream and its markers.

        A recording of that name that was already stored is not continued: a new one starts.
        """
        with self._live_lock:
            if self._recorder is not None:
                raise ConflictError(
                    f"already recording {self._recorder.name!r}: DELETE /live/recording first",
                    field="name",
                )
            self._remove_if_stored(self._recording_folder(name))
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
        """Names of recording folders not finalised (interrupted), except the current one and
        those already stored."""
        if not self.live_recordings.is_dir():
            return []
        current = self._recorder.name if self._recorder is not None else None
        return sorted(
            p.name
            for p in self.live_recordings.iterdir()
            if (p / INDEX_FILE).is_file() and p.name != current and self._stored_as(p) is None
        )

    def stop_recording(self, name: str | None = None) -> RecordingPublic:
        """Stop the live recording and store it as a BDF recording.

        With ``name`` and no recording in progress, finalise that interrupted recording
        (everything up to its last flushed block). The folder is removed once the BDF is
        stored; if storing fails it stays, so nothing is lost. Idempotent: the BDF's sha256
        is noted in the folder (:data:`STORED_FILE`) before it is stored, so a folder left
        by a crash after storing is recognised and removed, and its stored recording is the
        answer (as it is at the next start-up).
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
        stored = self._remove_if_stored(folder) if recorder is None else None
        if stored is not None:
            return stored
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
        sha = file_sha256(finalised.path)
        write_json_atomic(folder / STORED_FILE, {"sha256": sha})
        meta = self.recordings.add_bdf(
            finalised.path, filename=f"{name}.bdf", ch_names=eeg, notes=notes, sha256=sha
        )
        self._remove_folder(folder)
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
