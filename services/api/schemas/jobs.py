"""Schemas of jobs. Each kind's ``config`` model is the job contract's
(:mod:`services.platform.jobs`), shared with the worker, which parses a job's config with
the same model before it runs it."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, Field, computed_field

from services.api.schemas.common import ApiRequest, PublicModel
from services.core.db.models import JOB_FINAL_STATUSES, JOB_STATUSES
from services.platform.jobs import KindName, SubmittedKindName, job_kind
from services.platform.jobs.resource import FINAL_JOB_STATUSES, JobFields, JobStatus

assert set(JobStatus.__args__) == set(JOB_STATUSES)  # type: ignore[attr-defined]
assert set(JOB_FINAL_STATUSES) == FINAL_JOB_STATUSES


class JobKindPublic(BaseModel):
    """A job kind: its name, title, whether it counts environment steps, and the JSON Schema
    of its config (None: jobs of this kind are created by the platform, not submitted)."""

    name: KindName
    title: str
    submittable: bool
    counts_steps: bool = Field(description="Progress is environment steps (a learning curve).")
    config_schema: dict[str, Any] | None


class JobCreate(ApiRequest):
    """A job to run: its kind and that kind's config."""

    kind: SubmittedKindName
    config: dict[str, Any] = Field(default_factory=dict)


class JobPublic(PublicModel, JobFields):
    """A job: status, progress and where its results are (the curve has its own route)."""

    @computed_field(  # type: ignore[prop-decorator]
        description="What the job does, in one line (its kind's summary of its config), "
        "e.g. 'SSSG hf_sparse C=0.7 seed 3, 40,000 steps'."
    )
    @property
    def summary(self) -> str:
        try:
            kind = job_kind(self.kind)
        except ValueError:  # a row of a kind this version does not know
            return self.kind
        try:
            return kind.summary(self.config)
        except (TypeError, ValueError):  # a config stored before its kind's fields settled
            return kind.title


class CurvePublic(PublicModel):
    """The job's learning curve: ``[step, SPL]`` pairs of the greedy evaluations so far."""

    job_id: str
    curve: list[tuple[int, float]]


class JobLogEntry(BaseModel):
    """One event of a job: who submitted, cancelled or retried it, when it started, resumed,
    and how it ended."""

    at: datetime
    event: str = Field(description="submitted, cancel requested, retried, started, finished...")
    detail: str = ""
    actor_email: str | None = None


class JobLogPublic(BaseModel):
    """A job's events, oldest first."""

    job_id: str
    items: list[JobLogEntry]
