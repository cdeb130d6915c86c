"""The platform's job queue: Celery configured once for the api (client) and the workers.

The database row of a job is the truth; the broker only carries "job <id> has work to do".
Every task takes one argument, the job id, and is idempotent by it: a worker reloads the row,
claims a lease (``services.core.db.jobs``) and drops the message if the job is finished or
leased by a live worker. So a message delivered twice, or re-sent by the reaper after a
worker died, never runs a job twice at once.

Brokers: ``BGRL_BROKER_URL`` (Redis in a deployment, e.g. ``redis://127.0.0.1:6379/0``), or
by default kombu's filesystem transport under ``<data_dir>/broker``, which needs no server and
works between processes of one host. Its messages are written atomically here
(:class:`AtomicFilesystemTransport`): kombu's own writer creates the file before it writes
it, and a worker polling at that instant takes the empty file, loses the message and dies.
Neither broker is trusted to keep an unacknowledged message
when a worker is killed (the filesystem transport holds it in the dead process's memory,
Redis gives it back only after ``visibility_timeout``): the reaper of expired leases covers
both. Results are not stored in Celery (no result backend): they are written to the job row.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path
from time import monotonic
from typing import TYPE_CHECKING, Any

from celery import Celery
from kombu.transport import TRANSPORT_ALIASES, filesystem
from kombu.utils.encoding import str_to_bytes
from kombu.utils.json import dumps

if TYPE_CHECKING:
    from services.core.platform import PlatformSettings

TASK_PREFIX = "bgrl.jobs."
"""Celery task names are this and the job kind (the api sends by name; only workers import
the tasks, one per kind of ``services.platform.jobs``)."""


def task_name(kind: str) -> str:
    """The Celery task of job kind ``kind``."""
    return TASK_PREFIX + kind


JOB_QUEUE = "bgrl.jobs"
"""The one queue every job task goes to."""

REDIS_VISIBILITY_TIMEOUT_S = 3600
"""Redis gives an unacknowledged message to another worker after this long. Long jobs outlive
it, which is harmless: the second delivery finds the job leased and is dropped. A dead
worker's job is re-sent by the reaper as soon as its lease expires, not after this."""

FILESYSTEM_POLL_S = 0.2
"""How often a worker on the embedded filesystem broker looks for new messages."""


EMBEDDED_SCHEME = "bgrl-filesystem"
"""Transport alias of the embedded broker (kombu's filesystem transport, atomic writes)."""


class _AtomicFilesystemChannel(filesystem.Channel):
    """kombu's filesystem channel, but a message appears in the queue folder only complete:
    it is written under a name no reader matches, then renamed into place."""

    def _put(self, queue: str, payload: Any, **kwargs: Any) -> None:
        name = f"{round(monotonic() * 1000)}_{uuid.uuid4()}.{queue}.msg"
        folder = Path(self.data_folder_out)
        tmp = folder / f"incoming-{uuid.uuid4().hex}.part"
        try:
            with tmp.open("wb") as handle:
                handle.write(str_to_bytes(dumps(payload)))
            os.replace(tmp, folder / name)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise filesystem.ChannelError(f"cannot add a message to {folder}") from exc


class AtomicFilesystemTransport(filesystem.Transport):
    """The embedded broker's transport (see :class:`_AtomicFilesystemChannel`)."""

    Channel = _AtomicFilesystemChannel


TRANSPORT_ALIASES[EMBEDDED_SCHEME] = f"{__name__}:AtomicFilesystemTransport"


def embedded_broker_dir(settings: PlatformSettings) -> Path:
    """Folder of the embedded filesystem broker: ``<data_dir>/broker`` (absolute)."""
    return (settings.data_dir / "broker").resolve()


def broker_url(settings: PlatformSettings) -> str:
    """``BGRL_BROKER_URL``, or the embedded filesystem broker's URL."""
    return settings.broker_url or f"{EMBEDDED_SCHEME}://"


def uses_embedded_broker(settings: PlatformSettings) -> bool:
    """True when jobs go through the filesystem broker under the data folder."""
    return broker_url(settings).startswith((f"{EMBEDDED_SCHEME}:", "filesystem:"))


def _transport_options(settings: PlatformSettings) -> dict[str, Any]:
    if uses_embedded_broker(settings):
        root = embedded_broker_dir(settings)
        queue_dir = root / "queue"
        control_dir = root / "control"
        for folder in (queue_dir, control_dir):
            folder.mkdir(parents=True, exist_ok=True)
        return {
            "data_folder_in": str(queue_dir),
            "data_folder_out": str(queue_dir),
            "control_folder": str(control_dir),
            "store_processed": False,
            "polling_interval": FILESYSTEM_POLL_S,
        }
    if broker_url(settings).startswith(("redis:", "rediss:")):
        return {"visibility_timeout": REDIS_VISIBILITY_TIMEOUT_S}
    return {}


def make_celery(settings: PlatformSettings) -> Celery:
    """The Celery app of the platform; the api and every worker build it the same way.

    Reliability settings (all deliberate):

    * ``task_acks_late``: a message is acknowledged when its task returns, not when it is
      received, so a worker that dies mid-job does not acknowledge it;
    * ``task_reject_on_worker_lost``: a pool child killed mid-task puts its message back;
    * ``worker_prefetch_multiplier=1``: a worker holds only the message it is running;
    * no automatic Celery retries: the job row's ``attempts``/``max_attempts`` bound every
      re-run (worker crashes, failures and the reaper alike);
    * no result backend: the job row holds status, progress, result and errors.
    """
    app = Celery("bgrl", set_as_current=False)
    embedded = uses_embedded_broker(settings)
    app.conf.update(
        broker_url=broker_url(settings),
        broker_transport_options=_transport_options(settings),
        broker_connection_retry_on_startup=True,
        result_backend=None,
        task_ignore_result=True,
        task_store_errors_even_if_ignored=False,
        task_acks_late=True,
        task_acks_on_failure_or_timeout=True,
        task_reject_on_worker_lost=True,
        task_default_queue=JOB_QUEUE,
        task_routes={f"{TASK_PREFIX}*": {"queue": JOB_QUEUE}},
        task_serializer="json",
        accept_content=["json"],
        worker_prefetch_multiplier=1,
        worker_concurrency=1,
        worker_pool="solo",
        worker_hijack_root_logger=False,
        worker_redirect_stdouts=False,
        worker_enable_remote_control=not embedded,
        worker_send_task_events=not embedded,
        task_send_sent_event=not embedded,
        worker_cancel_long_running_tasks_on_connection_loss=False,
        enable_utc=True,
        timezone="UTC",
    )
    return app


def enqueue_job(celery_app: Celery, job_id: str, kind: str) -> None:
    """Send the task of ``kind`` for ``job_id``; call it after the job row is committed."""
    celery_app.send_task(task_name(kind), args=[job_id], queue=JOB_QUEUE)
