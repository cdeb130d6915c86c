"""The reaper of dead workers' jobs, a thread run by every worker and by ``bgrl up`` itself.

Each pass runs :func:`services.core.db.jobs.reap`: a running job whose lease expired goes
back to the queue (or fails with the reason when its attempts are spent), a waiting parent
whose children are final is sent again, and a queued job untouched for ``stale_queued_s`` is
sent again. Several reapers may run at once (every change is a conditional update). In
``bgrl up`` it lives in the supervisor, so it runs whichever child process died, even while
no worker is left.
"""

from __future__ import annotations

import logging
import threading

from celery import Celery
from sqlalchemy.orm import Session, sessionmaker

from services.core.db import jobs as job_rows
from services.core.queue import enqueue_job

logger = logging.getLogger(__name__)


class Reaper(threading.Thread):
    """Re-sends jobs that dead workers left behind, every ``interval_s`` until stopped."""

    def __init__(
        self,
        sessions: sessionmaker[Session],
        celery: Celery,
        *,
        interval_s: float,
        stale_queued_s: float,
    ) -> None:
        super().__init__(name="reaper", daemon=True)
        self.sessions = sessions
        self.celery = celery
        self.interval_s = interval_s
        self.stale_queued_s = stale_queued_s
        self._done = threading.Event()
        self._resend = threading.Event()

    def run(self) -> None:
        while not self._done.wait(self.interval_s):
            try:
                self.reap_once()
            except Exception:
                logger.exception("reaper pass failed")

    def resend_queued_soon(self) -> None:
        """Have the next pass send every queued job again: a worker died, and the messages
        it had taken but not claimed died with it (the file broker deletes a message once
        taken; Redis returns it only after an hour). The claim drops duplicates."""
        self._resend.set()

    def reap_once(self) -> list[tuple[str, str]]:
        """One pass; the ``(job id, kind)`` sent again."""
        resend = self._resend.is_set()
        self._resend.clear()
        stale_queued_s = 0.0 if resend else self.stale_queued_s
        with self.sessions() as session:
            to_send = job_rows.reap(session, stale_queued_s=stale_queued_s)
        for job_id, kind in to_send:
            logger.info("reaper: sending job %s (%s) again", job_id, kind)
            enqueue_job(self.celery, job_id, kind)
        return to_send

    def stop(self) -> None:
        self._done.set()
