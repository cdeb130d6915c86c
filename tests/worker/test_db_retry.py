"""A job's message survives a database that cannot be reached when the task starts."""

from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy.exc import OperationalError

from services.core.queue import task_name
from services.worker.app import DB_RETRIES, HANDLERS, create_runtime
from services.worker.settings import WorkerSettings


def test_every_job_task_is_sent_again_while_the_database_cannot_be_reached(
    tmp_path: Path,
) -> None:
    # a PostgreSQL server that is not there: the claim raises OperationalError
    settings = WorkerSettings(
        data_dir=tmp_path, database_url="postgresql+psycopg://nobody@127.0.0.1:1/none"
    )
    runtime = create_runtime(settings)
    for kind in HANDLERS:
        task = runtime.celery.tasks[task_name(kind)]
        assert task.autoretry_for == (OperationalError,) and task.max_retries == DB_RETRIES
    task = runtime.celery.tasks[task_name(next(iter(HANDLERS)))]
    sent_again: list[dict] = []
    task.retry = lambda **options: (
        sent_again.append(options) or (_ for _ in ()).throw(RuntimeError("sent again"))
    )
    with pytest.raises(RuntimeError, match="sent again"):
        task.run("no-such-job")
    assert isinstance(sent_again[0]["exc"], OperationalError)
    assert sent_again[0]["countdown"] == 1  # then 2, 4 ... 30 s
