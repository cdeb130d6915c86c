"""The job resource the api returns (``GET /api/v1/jobs/{id}``, the job list's items): its
fields, defined once for the api, which builds it from a job row, and the Python client,
which reads it."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel

JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]
"""A job's status (the database's ``JOB_STATUSES``, checked equal by the api's schemas; this
module imports no database code, so the client installs without it)."""
FINAL_JOB_STATUSES: frozenset[str] = frozenset({"succeeded", "failed", "cancelled"})
"""A job in one of these stays there (until it is retried)."""


class JobFields(BaseModel):
    """A job: status, progress and where its results are (the curve has its own route)."""

    id: str
    kind: str
    config: dict[str, Any]
    status: JobStatus
    progress: float
    attempts: int
    max_attempts: int
    resumed_from_step: int | None
    steps_done: int
    error: str | None
    result: dict[str, Any] | None
    submitter_id: int | None
    parent_id: str | None
    cancel_requested: bool
    checkpoint_artifact_id: str | None
    model_artifact_id: str | None
    created_at: datetime
    updated_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
