"""How a worker runs one job: claim the lease, keep it alive, write the row, end it.

:func:`run_job` is what every Celery task does with its job id. While the handler of the job's
kind runs, a :class:`LeaseKeeper` thread heartbeats the lease (at most 1 s apart), notices a
cancel request or a lost lease, and records the latest checkpoint as an artifact. The
handler polls :attr:`JobContext.stopped` (training does on every step) and returns; the job
then ends cancelled, or, if the lease was lost to another worker, without writing anything.
"""

from __future__ import annotations

import logging
import threading
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

from celery import Celery
from pydantic import ValidationError
from sqlalchemy import Engine, select
from sqlalchemy.orm import Session, sessionmaker

from services.core.artifacts import ArtifactStore, job_folder, sha256_file
from services.core.db import jobs as job_rows
from services.core.db.models import JOB_FINAL_STATUSES, Artifact, Job
from services.core.db.session import make_engine, make_session_factory
from services.core.queue import enqueue_job
from services.core.web import jsonable
from services.platform.jobs import JobKind, config_error
from services.worker.settings import WorkerSettings

logger = logging.getLogger(__name__)

MAX_BEAT_S = 1.0
"""Heartbeats (and cancel checks) are at most this far apart, so cancel acts within 5 s."""

SHUTDOWN = threading.Event()
"""Set when this worker is asked to stop: the running job is handed back to the queue."""


class JobConfigError(ValueError):
    """The job's config is invalid: the job fails at once, without retries."""


def parse_config(kind: JobKind, config: dict[str, Any]) -> Any:
    """The job's config parsed with its kind's model (the api's validation, again: a config
    stored by an older api, or written by hand, is refused the same way)."""
    try:
        return kind.parse(config)
    except ValidationError as exc:
        raise JobConfigError(config_error(exc)) from None


class JobStoppedError(Exception):
    """The job must stop: cancel was requested, or the lease was lost."""


@dataclass
class Runtime:
    """Per-process resources of a worker: settings, database, artifact store, Celery app."""

    settings: WorkerSettings
    celery: Celery

    @cached_property
    def engine(self) -> Engine:
        return make_engine(self.settings.resolved_database_url)

    @cached_property
    def sessions(self) -> sessionmaker[Session]:
        return make_session_factory(self.engine)

    @cached_property
    def store(self) -> ArtifactStore:
        return ArtifactStore(self.settings.resolved_artifact_dir)

    @cached_property
    def owner(self) -> str:
        return self.settings.owner_name

    @property
    def lease_s(self) -> float:
        return self.settings.job_lease_s

    @property
    def beat_s(self) -> float:
        return min(self.settings.job_heartbeat_s, MAX_BEAT_S)


@dataclass
class JobOutcome:
    """What a handler returns: the job's result and other columns to set when it succeeds."""

    result: dict[str, Any] | None = None
    values: dict[str, Any] = field(default_factory=dict)
    error: str | None = None
    """Set: the job ends ``failed`` with this error (and its result kept)."""
    wait_for_children: bool = False
    """True: the job fanned out child jobs and waits for them, holding no lease."""


class LeaseKeeper(threading.Thread):
    """Heartbeats a job's lease; sets ``stop_reason`` on cancel or when the lease is lost."""

    def __init__(self, runtime: Runtime, job_id: str) -> None:
        super().__init__(name=f"lease-{job_id[:8]}", daemon=True)
        self.runtime = runtime
        self.job_id = job_id
        self.stop_reason: str | None = None
        self.checkpoint: Path | None = None
        self.checkpoint_kind = "checkpoint"
        self._checkpoint_seen: tuple[int, int] | None = None
        self._done = threading.Event()
        self._woken = threading.Event()

    def run(self) -> None:
        while not self._done.wait(self.runtime.beat_s):
            try:
                self.beat()
            except Exception:  # a database hiccup: the lease has slack, try again next beat
                logger.exception("job %s: heartbeat failed", self.job_id)

    def beat(self) -> None:
        with self.runtime.sessions() as session:
            answer = job_rows.heartbeat(
                session, self.job_id, self.runtime.owner, self.runtime.lease_s
            )
        if not answer.held:
            self.stop_reason = "lease lost"
        elif answer.cancel_requested and self.stop_reason is None:
            self.stop_reason = "cancelled"
        if answer.held:
            self.record_checkpoint()

    def record_checkpoint(self) -> None:
        """Register the checkpoint file as the job's checkpoint artifact when it changed."""
        if self.checkpoint is None or not self.checkpoint.exists():
            return
        stat = self.checkpoint.stat()
        seen = (stat.st_mtime_ns, stat.st_size)
        if seen == self._checkpoint_seen:
            return
        self._checkpoint_seen = seen
        artifact_id = register_artifact(
            self.runtime, self.job_id, self.checkpoint, kind=self.checkpoint_kind
        )
        with self.runtime.sessions() as session:
            job_rows.update_job(
                session, self.job_id, self.runtime.owner, checkpoint_artifact_id=artifact_id
            )

    def finish(self) -> None:
        self._done.set()
        self.join(timeout=10)


def register_artifact(runtime: Runtime, job_id: str, path: Path, *, kind: str) -> str:
    """Create or refresh the Artifact row of a file already in the store; returns its id."""
    relpath = path.resolve().relative_to(runtime.store.root).as_posix()
    digest, size = sha256_file(path), path.stat().st_size
    with runtime.sessions() as session:
        artifact = session.scalar(select(Artifact).where(Artifact.relpath == relpath))
        if artifact is None:
            owner_id = session.scalar(select(Job.submitter_id).where(Job.id == job_id))
            artifact = Artifact(
                kind=kind,
                relpath=relpath,
                sha256=digest,
                size_bytes=size,
                owner_id=owner_id,
                job_id=job_id,
            )
            session.add(artifact)
        else:
            artifact.sha256, artifact.size_bytes = digest, size
        session.commit()
        return artifact.id


@dataclass
class JobContext:
    """What a handler gets: the job's row as claimed, and ways to report on it."""

    runtime: Runtime
    job_id: str
    kind: str
    config: dict[str, Any]
    submitter_id: int | None
    parent_id: str | None
    max_attempts: int
    keeper: LeaseKeeper
    attempt: int = 1
    """Which attempt this is (1 for the first); ``attempt == max_attempts``: the last."""

    @property
    def stop_reason(self) -> str | None:
        """Why the job must stop: ``cancelled``, ``lease lost``, ``shutdown``; None: go on."""
        return self.keeper.stop_reason or ("shutdown" if SHUTDOWN.is_set() else None)

    @property
    def stopped(self) -> bool:
        """True once the job must stop."""
        return self.stop_reason is not None

    def check_stop(self) -> None:
        """Raise :class:`JobStoppedError` if the job must stop."""
        reason = self.stop_reason
        if reason is not None:
            raise JobStoppedError(reason)

    def update(self, **values: Any) -> None:
        """Write columns of the job row (under the lease)."""
        with self.runtime.sessions() as session:
            if not job_rows.update_job(session, self.job_id, self.runtime.owner, **values):
                self.keeper.stop_reason = "lease lost"
                raise JobStoppedError("lease lost")

    def job_dir(self, kind: str) -> Path:
        """This job's folder of ``kind`` files in the artifact store (created)."""
        folder = self.runtime.store.path(job_folder(kind, self.job_id))
        folder.mkdir(parents=True, exist_ok=True)
        return folder

    def store_file(self, src: Path, *, kind: str, name: str) -> str:
        """Move ``src`` into the artifact store as an artifact of this job; returns its id."""
        stored = self.runtime.store.put_file(src, kind=kind, name=name, move=True)
        with self.runtime.sessions() as session:
            artifact = Artifact(
                kind=kind,
                relpath=stored.relpath,
                sha256=stored.sha256,
                size_bytes=stored.size_bytes,
                owner_id=self.submitter_id,
                job_id=self.job_id,
            )
            session.add(artifact)
            session.commit()
            return artifact.id

    def watch_checkpoint(self, path: Path) -> None:
        """Record ``path`` as the job's checkpoint artifact whenever it is rewritten."""
        self.keeper.checkpoint = path


Handler = Callable[[JobContext], JobOutcome]


def run_job(runtime: Runtime, job_id: str, handler: Handler) -> str:
    """Claim ``job_id`` and run ``handler`` on it; returns what happened (for logs and tests).

    Idempotent by job id: a finished job, or one leased by a live worker, is left alone.
    """
    with runtime.sessions() as session:
        claim = job_rows.claim_job(session, job_id, runtime.owner, runtime.lease_s)
        if claim is not job_rows.ClaimOutcome.CLAIMED:
            logger.info("job %s: not run (%s)", job_id, claim.value)
            return claim.value
        job = session.get(Job, job_id, populate_existing=True)
        assert job is not None
        keeper = LeaseKeeper(runtime, job_id)
        config = job.config if job.config is not None else {}
        context = JobContext(
            runtime=runtime,
            job_id=job_id,
            kind=job.kind,
            config=dict(config) if isinstance(config, dict) else {},
            submitter_id=job.submitter_id,
            parent_id=job.parent_id,
            max_attempts=job.max_attempts,
            keeper=keeper,
            attempt=job.attempts,
        )
        logger.info("job %s (%s): attempt %d started", job_id, job.kind, job.attempts)
    if not isinstance(config, dict):  # written around the api (an old version, by hand)
        error = f"config must be a JSON object of settings, not {type(config).__name__}"
        with runtime.sessions() as session:
            job_rows.finish_job(session, job_id, runtime.owner, "failed", error=error)
        logger.warning("job %s: invalid config: %s", job_id, error)
        _notify_parent(runtime, context.parent_id)
        return "failed"
    keeper.start()
    try:
        outcome = handler(context)
        context.check_stop()
    except JobStoppedError as stop:
        keeper.finish()
        return _end_stopped(context, str(stop))
    except JobConfigError as exc:
        keeper.finish()
        with runtime.sessions() as session:
            job_rows.finish_job(session, job_id, runtime.owner, "failed", error=str(exc))
        logger.warning("job %s: invalid config: %s", job_id, exc)
        _notify_parent(runtime, context.parent_id)
        return "failed"
    except Exception as exc:
        keeper.finish()
        if context.stop_reason is not None:  # the error came from being stopped
            return _end_stopped(context, context.stop_reason)
        logger.exception("job %s: attempt failed", job_id)
        with runtime.sessions() as session:
            status = job_rows.release_for_retry(
                session,
                job_id,
                runtime.owner,
                error=f"{type(exc).__name__}: {exc}",
                traceback=traceback.format_exc(),
            )
        if status == "queued":
            enqueue_job(runtime.celery, job_id, context.kind)
        elif status == "failed":
            _notify_parent(runtime, context.parent_id)
        return status or "lease lost"
    keeper.finish()
    keeper.record_checkpoint()
    with runtime.sessions() as session:
        if outcome.wait_for_children:
            job_rows.wait_for_children(session, job_id, runtime.owner, **outcome.values)
            logger.info("job %s: waiting for its child jobs", job_id)
            return "waiting"
        status = "failed" if outcome.error else "succeeded"
        done = job_rows.finish_job(
            session,
            job_id,
            runtime.owner,
            status,
            result=jsonable(outcome.result) if outcome.result is not None else None,
            error=outcome.error,
            **outcome.values,
        )
    logger.info("job %s: %s", job_id, status if done else "lease lost before the end")
    if done:
        _notify_parent(runtime, context.parent_id)
    return status if done else "lease lost"


def _end_stopped(context: JobContext, reason: str) -> str:
    runtime = context.runtime
    if reason == "lease lost":
        logger.warning("job %s: lease lost; another worker owns it now", context.job_id)
        return "lease lost"
    if reason == "shutdown":
        with runtime.sessions() as session:
            handed_back = job_rows.hand_back(session, context.job_id, runtime.owner)
        if handed_back:
            enqueue_job(runtime.celery, context.job_id, context.kind)
            logger.info("job %s: handed back to the queue (worker stopping)", context.job_id)
        return "handed back"
    with runtime.sessions() as session:
        job_rows.finish_job(session, context.job_id, runtime.owner, "cancelled")
    logger.info("job %s: cancelled", context.job_id)
    _notify_parent(runtime, context.parent_id)
    return "cancelled"


def _notify_parent(runtime: Runtime, parent_id: str | None) -> None:
    """Send the parent job again once all its children are final (it then aggregates)."""
    if parent_id is None:
        return
    with runtime.sessions() as session:
        counts = job_rows.children_status(session, parent_id)
        parent_kind = session.scalar(select(Job.kind).where(Job.id == parent_id))
    if parent_kind is not None and all(s in JOB_FINAL_STATUSES for s in counts):
        enqueue_job(runtime.celery, parent_id, parent_kind)
