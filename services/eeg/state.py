"""The state of one EEG service instance: its stores, job runner and live session."""

from __future__ import annotations

import asyncio
import logging
import threading

from services.core.artifacts import ArtifactStore
from services.eeg.jobs import JobRunner
from services.eeg.live_session import FeedbackHub, LiveSession
from services.eeg.settings import EEGSettings
from services.eeg.store import ClassifierStore, JobStore, RecordingStore

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

    @property
    def live(self) -> LiveSession | None:
        """The current live session (possibly disconnected), or None."""
        return self._live

    def set_live(self, session: LiveSession | None, reason: str) -> None:
        """Make ``session`` the live session; the previous one is closed with ``reason``."""
        with self._live_lock:
            previous, self._live = self._live, session
        if previous is not None:
            logger.info("closing the %s live source: %s", previous.source, reason)
            previous.close(reason)

    def close(self) -> None:
        """Release the live source and stop the job runner."""
        try:
            self.set_live(None, "the EEG service is stopping")
        finally:
            self.runner.close()
