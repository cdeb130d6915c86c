"""Calibration jobs: run one at a time in a worker thread, cancellable, recorded on disk.

A job goes ``queued`` -> ``running`` -> ``succeeded`` | ``failed`` | ``cancelled``. Every
change is written to its record (:class:`~services.eeg.service.store.JobStore`) under the store's
lock, so a cancel never races with the worker picking the job up. A failed job keeps its
error (one line) and traceback; a job cut off by a restart or a shutdown is marked failed
with that reason; a cancelled or failed job leaves no classifier behind.
"""

from __future__ import annotations

import logging
import threading
import traceback
import uuid
from concurrent.futures import Future, ThreadPoolExecutor

from services.core.web import jsonable
from services.eeg.decoding.calibration import CalibrationCancelled, TrainingConfig, calibrate
from services.eeg.recordings.io import read_recording
from services.eeg.service.errors import JobStateError
from services.eeg.service.schemas import FINAL_JOB_STATUSES, JobCreate, JobPublic
from services.eeg.service.store import ClassifierStore, JobStore, RecordingStore, utc_now

logger = logging.getLogger(__name__)

INTERRUPTED = "interrupted: the EEG service stopped before the job finished; start a new job"


class JobRunner:
    """Runs calibration jobs in one background thread."""

    def __init__(
        self, jobs: JobStore, recordings: RecordingStore, classifiers: ClassifierStore
    ) -> None:
        self.jobs = jobs
        self.recordings = recordings
        self.classifiers = classifiers
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="calibration")
        self._futures: dict[str, Future[None]] = {}
        self._stop: dict[str, threading.Event] = {}
        self._closing = False
        self.fail_unfinished()

    def submit(self, body: JobCreate) -> JobPublic:
        """Record a new job for a stored recording and queue it."""
        self.recordings.get(body.recording_id)
        job = JobPublic(
            id=uuid.uuid4().hex[:16],
            recording_id=body.recording_id,
            seed=body.seed,
            max_passes=body.max_passes,
            status="queued",
            created_at=utc_now(),
        )
        with self.jobs.lock:
            self.jobs.save(job)
            self._stop[job.id] = threading.Event()
            self._futures[job.id] = self._executor.submit(self._run, job.id)
        logger.info("job %s queued (recording %s)", job.id, job.recording_id[:12])
        return job

    def cancel(self, job_id: str) -> JobPublic:
        """Cancel a job: a queued one at once, a running one after its current pass."""
        with self.jobs.lock:
            job = self.jobs.get(job_id)
            if job.status in FINAL_JOB_STATUSES:
                raise JobStateError(f"job {job_id!r} is already {job.status}", field="job_id")
            stop = self._stop.get(job_id)
            if stop is not None:
                stop.set()
            future = self._futures.get(job_id)
            if job.status == "queued":
                if future is not None:
                    future.cancel()
                job = self.jobs.save(
                    job.model_copy(
                        update={
                            "status": "cancelled",
                            "cancel_requested": True,
                            "finished_at": utc_now(),
                        }
                    )
                )
            else:
                job = self.jobs.save(job.model_copy(update={"cancel_requested": True}))
        logger.info("job %s: cancel requested (%s)", job_id, job.status)
        return job

    def _run(self, job_id: str) -> None:
        with self.jobs.lock:
            job = self.jobs.get(job_id)
            if job.status != "queued":  # cancelled while it waited
                return
            job = self.jobs.update(job_id, status="running", started_at=utc_now())
            stop = self._stop[job_id]
        logger.info("job %s running", job_id)
        try:
            raw = read_recording(self.recordings.file(job.recording_id))
            if stop.is_set():
                raise CalibrationCancelled("cancelled before training")
            result = calibrate(
                raw,
                seed=job.seed,
                out_dir=self.classifiers.staging(job_id),
                config=TrainingConfig(max_passes=job.max_passes),
                report=True,
                should_stop=stop.is_set,
            )
            del raw
            classifier_id = self.classifiers.publish(job_id, job.recording_id)
            self._finish(
                job_id, "succeeded", classifier_id=classifier_id, metrics=jsonable(result.metrics)
            )
        except CalibrationCancelled:
            self.classifiers.discard(job_id)
            if self._closing:
                self._finish(job_id, "failed", error=INTERRUPTED)
            else:
                self._finish(job_id, "cancelled")
        except Exception as exc:
            self.classifiers.discard(job_id)
            logger.exception("job %s failed", job_id)
            line = f"{type(exc).__name__}: {exc}".splitlines()[0]
            self._finish(job_id, "failed", error=line, traceback=traceback.format_exc())
        finally:
            with self.jobs.lock:
                self._stop.pop(job_id, None)
                self._futures.pop(job_id, None)

    def _finish(self, job_id: str, status: str, **changes: object) -> None:
        self.jobs.update(job_id, status=status, finished_at=utc_now(), **changes)
        logger.info("job %s %s", job_id, status)

    def fail_unfinished(self) -> None:
        """Mark jobs left queued or running (by a previous process) as failed, with the reason.

        Such a job can never finish (the worker thread died with its process); its
        half-written classifier is removed and the recording stays stored for a new job.
        """
        with self.jobs.lock:
            for job in self.jobs.list():
                if job.status in ("queued", "running") and job.id not in self._futures:
                    self.classifiers.discard(job.id)
                    self.jobs.save(
                        job.model_copy(
                            update={
                                "status": "failed",
                                "error": INTERRUPTED,
                                "finished_at": utc_now(),
                            }
                        )
                    )
                    logger.warning("job %s was interrupted by a restart", job.id)

    def close(self) -> None:
        """Stop the running job after its current pass, drop queued ones (marked failed)."""
        with self.jobs.lock:
            self._closing = True
            for stop in self._stop.values():
                stop.set()
        self._executor.shutdown(wait=True, cancel_futures=True)
        with self.jobs.lock:
            self._futures.clear()
        self.fail_unfinished()
