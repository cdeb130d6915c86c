"""Job kinds: each kind's title and the JSON Schema of its config (the job contract's,
:mod:`services.platform.jobs`), from which clients build their job forms."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from services.api.deps import get_current_user
from services.api.schemas.jobs import JobKindPublic
from services.platform.jobs import JOB_KINDS

router = APIRouter(
    prefix="/api/v1/job-kinds", tags=["jobs"], dependencies=[Depends(get_current_user)]
)

KINDS_PUBLIC: list[JobKindPublic] = [
    JobKindPublic(
        name=kind.name,  # type: ignore[arg-type]
        title=kind.title,
        submittable=kind.submittable,
        counts_steps=kind.counts_steps,
        config_schema=kind.config.model_json_schema() if kind.config is not None else None,
    )
    for kind in JOB_KINDS.values()
]
"""The answer, built once (the kinds do not change while the api runs)."""


@router.get("")
def list_job_kinds() -> list[JobKindPublic]:
    """Every job kind, in the order the dashboard lists them; submit the submittable ones
    with ``POST /api/v1/jobs`` and a config valid against ``config_schema``."""
    return KINDS_PUBLIC
