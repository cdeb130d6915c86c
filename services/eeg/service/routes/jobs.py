"""Calibration jobs: start, list, inspect, cancel."""

from __future__ import annotations

from fastapi import APIRouter, status

from services.core.disk import require_free_space
from services.core.errors import BadRequestError
from services.eeg.service.deps import JobsDep, RunnerDep, SettingsDep
from services.eeg.service.schemas import JobCreate, JobPublic

router = APIRouter(prefix="/jobs", tags=["jobs"])


@router.post("", status_code=status.HTTP_202_ACCEPTED)
def start_job(body: JobCreate, runner: RunnerDep, settings: SettingsDep) -> JobPublic:
    """Start calibration training on a stored recording, in the background.

    Refused with 507 while the data disk keeps less than ``BGRL_MIN_FREE_MB`` free.
    """
    require_free_space(
        settings.eeg_dir, min_free_mb=settings.min_free_mb, refusing="a new calibration job"
    )
    if body.max_passes > settings.max_training_passes:
        raise BadRequestError(
            f"max_passes may be at most {settings.max_training_passes}", field="max_passes"
        )
    return runner.submit(body)


@router.get("")
def list_jobs(jobs: JobsDep) -> list[JobPublic]:
    """Every job, oldest first."""
    return jobs.list()


@router.get("/{job_id}")
def read_job(job_id: str, jobs: JobsDep) -> JobPublic:
    """One job: status, and metrics, classifier or error once it is over."""
    return jobs.get(job_id)


@router.post("/{job_id}/cancel")
def cancel_job(job_id: str, runner: RunnerDep) -> JobPublic:
    """Cancel a job: a queued one at once, a running one after its current training pass
    (``cancel_requested`` is true until then); 409 if it is already over."""
    return runner.cancel(job_id)
