"""The worker's Celery app: one task per job kind, and the reaper of dead workers' jobs.

Start a worker with ``bgrl worker`` (or ``celery -A services.worker.app worker``). Each task
takes a job id and runs :func:`services.worker.runtime.run_job` with the handler of its
kind. Every worker process also runs the reaper (:mod:`services.core.reaper`) every
``reaper_interval_s``: it re-sends jobs whose lease expired (their worker died) and parents
whose child jobs are all final.
"""

from __future__ import annotations

import importlib
import logging
from typing import Any

import torch
from celery import Celery
from celery.signals import worker_ready, worker_shutdown, worker_shutting_down
from sqlalchemy.exc import OperationalError

from services.core.gc_pauses import freeze_startup_objects, unfreeze
from services.core.queue import make_celery, task_name
from services.core.reaper import Reaper
from services.core.settings import load_settings
from services.platform.jobs import (
    BIDS_EXPORT,
    EEG_CALIBRATION,
    GUIDED_PPO,
    JOB_KINDS,
    LIVE_SESSION,
    REPRODUCE,
    REPRODUCE_BATCH,
    REPRODUCE_RUN,
    SESSION_REPLAY,
)
from services.worker.runtime import SHUTDOWN, Handler, Runtime, run_job
from services.worker.settings import WorkerSettings

logger = logging.getLogger(__name__)

HANDLERS: dict[str, str] = {
    GUIDED_PPO.name: "services.worker.training:guided_ppo",
    REPRODUCE.name: "services.worker.reproduce:reproduce",
    REPRODUCE_RUN.name: "services.worker.training:reproduce_run",
    REPRODUCE_BATCH.name: "services.worker.reproduce_batch:reproduce_batch",
    EEG_CALIBRATION.name: "services.worker.calibration:eeg_calibration",
    LIVE_SESSION.name: "services.worker.live_session:live_session",
    BIDS_EXPORT.name: "services.worker.bids:bids_export",
    SESSION_REPLAY.name: "services.worker.replay:session_replay",
}
assert set(HANDLERS) == set(JOB_KINDS), "every job kind of the registry needs its handler"
"""Handler of each job kind, imported on first use (a worker that only trains never loads
the EEG pipeline, which takes seconds to import)."""


def load_handler(kind: str) -> Handler:
    """The handler function of a job kind."""
    module, _, name = HANDLERS[kind].partition(":")
    handler: Handler = getattr(importlib.import_module(module), name)
    return handler


DB_RETRIES = 240
"""Times a job's message is sent again while the database cannot be reached (~2 h)."""


def create_runtime(settings: WorkerSettings | None = None) -> Runtime:
    """The worker runtime (settings from the environment unless given) with its tasks."""
    settings = settings or load_settings(WorkerSettings)
    celery = make_celery(settings)
    runtime = Runtime(settings=settings, celery=celery)
    for kind in HANDLERS:
        _register(celery, runtime, kind)
    return runtime


def _register(celery: Celery, runtime: Runtime, kind: str) -> None:
    def task(job_id: str) -> str:
        return run_job(runtime, job_id, load_handler(kind))

    task.__name__ = task.__qualname__ = kind
    task.__doc__ = f"Run the {kind} job with this id (idempotent by job id)."
    # A database that cannot be reached (restarting, cut off) before the job is claimed or
    # after it was released would end the task with its message acknowledged and the job
    # queued with no message for stale_queued_s (15 min): Celery sends the message again
    # instead, after 1, 2, 4 ... 30 s, for up to two hours; a repeat of a job that is
    # running or finished is dropped by the claim.
    celery.task(
        name=task_name(kind),
        autoretry_for=(OperationalError,),
        retry_backoff=1,
        retry_backoff_max=30,
        retry_jitter=False,
        max_retries=DB_RETRIES,
    )(task)


runtime: Runtime | None = None
"""This process's runtime, created by :func:`main_app` (a worker builds one at start)."""


def main_app(settings: WorkerSettings | None = None) -> Celery:
    """The Celery app of this worker process, created once (settings from the environment
    unless given); sets the process's torch thread count."""
    global runtime
    if runtime is None:
        runtime = create_runtime(settings)
        torch.set_num_threads(runtime.settings.worker_torch_threads)
    return runtime.celery


_reaper: Reaper | None = None


@worker_ready.connect
def _start_reaper(**_: Any) -> None:
    global _reaper
    if runtime is not None and _reaper is None:
        _reaper = Reaper(
            runtime.sessions,
            runtime.celery,
            interval_s=runtime.settings.reaper_interval_s,
            stale_queued_s=runtime.settings.stale_queued_s,
        )
        _reaper.start()
    if runtime is not None and runtime.settings.ready_file is not None:
        runtime.settings.ready_file.touch()
    # a full collection walks torch's, MNE's and SQLAlchemy's objects: 100+ ms mid-job
    freeze_startup_objects()


@worker_shutting_down.connect
def _hand_back_running_job(**_: Any) -> None:
    """Ctrl-C / SIGTERM: the running job stops at its next step and goes back to the queue
    (it resumes from its checkpoint on the next worker) instead of holding the stop."""
    SHUTDOWN.set()


@worker_shutdown.connect
def _stop_reaper(**_: Any) -> None:
    if _reaper is not None:
        _reaper.stop()
    unfreeze()


def __getattr__(name: str) -> Any:
    """``celery -A services.worker.app`` finds the app as ``app`` (built on first use)."""
    if name in ("app", "celery"):
        return main_app()
    raise AttributeError(name)
