"""Typed objects the platform's api returns (mirrors of its ``*Public`` schemas).

Unknown fields are ignored, so a newer api with more fields does not break older scripts.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any, Generic, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field

from services.platform.jobs import SubmittedKindName
from services.platform.jobs.resource import FINAL_JOB_STATUSES, JobFields
from services.platform.jobs.resource import JobStatus as JobStatus  # re-exported

ItemT = TypeVar("ItemT")

JobKind = SubmittedKindName
"""Kinds a user may submit (the job contract's, :mod:`services.platform.jobs`)."""


class ApiObject(BaseModel):
    """Something the api returned; extra fields are ignored."""

    model_config = ConfigDict(extra="ignore", frozen=True)


class Page(ApiObject, Generic[ItemT]):
    """One page of a list: ``items`` from ``offset`` and the ``total`` matching the filters."""

    items: list[ItemT]
    total: int
    limit: int
    offset: int


class AccessToken(ApiObject):
    """A short-lived bearer token from the login route."""

    access_token: str
    token_type: str = "bearer"
    expires_at: datetime


class User(ApiObject):
    """An account."""

    id: int
    email: str
    role: Literal["admin", "staff", "viewer"]
    active: bool
    created_at: datetime
    last_login_at: datetime | None = None


class ApiToken(ApiObject):
    """An API token as listed; ``token`` is set only in the answer that created it."""

    id: int
    user_id: int
    name: str
    token_prefix: str
    created_at: datetime
    expires_at: datetime | None = None
    revoked_at: datetime | None = None
    last_used_at: datetime | None = None
    token: str | None = None


class Subject(ApiObject):
    """A participant, known by a pseudonymous code."""

    id: int
    code: str
    notes: str
    created_at: datetime
    updated_at: datetime


class LabSession(ApiObject):
    """A scheduled (or past) lab session."""

    id: int
    subject_id: int
    rig_id: int | None
    kind: Literal["calibration", "test", "online", "rl"]
    scheduled_at: datetime
    duration_minutes: int
    ends_at: datetime
    status: Literal["scheduled", "running", "completed", "cancelled", "failed"]
    operator_id: int | None
    notes: str
    created_at: datetime
    updated_at: datetime


class Job(ApiObject, JobFields):
    """A job: its status, progress and where its results are."""

    summary: str = ""
    """What the job does, in one line (empty from a server older than 2026-12-03)."""

    @property
    def finished(self) -> bool:
        """True when the job has succeeded, failed or been cancelled."""
        return self.status in FINAL_JOB_STATUSES


class JobLogEntry(ApiObject):
    """One event of a job (submitted, cancel requested, retried, started, how it ended)."""

    at: datetime
    event: str
    detail: str = ""
    actor_email: str | None = None


class JobLog(ApiObject):
    """A job's events, oldest first."""

    job_id: str
    items: list[JobLogEntry]


class Curve(ApiObject):
    """A job's learning curve: ``(step, SPL)`` pairs of its greedy evaluations so far."""

    job_id: str
    curve: list[tuple[int, float]]


class Artifact(ApiObject):
    """A stored file and its checksum."""

    id: str
    kind: str
    relpath: str
    sha256: str
    size_bytes: int
    owner_id: int | None
    job_id: str | None
    created_at: datetime


class HFModel(ApiObject):
    """A human-feedback policy pi_HF with its metrics."""

    id: int
    name: str
    task: str
    feedback_accuracy: float | None
    n_labels: int | None
    session_id: int | None
    job_id: str | None
    torchscript_artifact_id: str | None
    onnx_artifact_id: str | None
    pt2_artifact_id: str | None
    metrics: dict[str, Any] = Field(default_factory=dict)
    created_at: datetime


class Classifier(ApiObject):
    """An ErrP classifier with its validation metrics."""

    id: int
    name: str
    subject_id: int | None
    recording_id: int | None
    job_id: str | None
    onnx_artifact_id: str | None
    torchscript_artifact_id: str | None
    pt2_artifact_id: str | None
    metrics: dict[str, Any] = Field(default_factory=dict)
    created_at: datetime
