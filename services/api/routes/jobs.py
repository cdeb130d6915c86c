"""Jobs: submit (committed, then enqueued on Celery), follow, cancel, retry, fetch results."""

from __future__ import annotations

import csv
import functools
import hashlib
import io
import logging
import math
import zipfile
from typing import Annotated, Any, Literal

from celery import Celery
from fastapi import APIRouter, Depends, Query, Response, status
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse
from pydantic import TypeAdapter, ValidationError
from sqlalchemy import bindparam, func, select, update
from sqlalchemy.orm import Session

from services.api import audit
from services.api.crud import PageQuery, get_by_id_or_prefix
from services.api.deps import (
    CeleryDep,
    DbDep,
    PageDep,
    SettingsDep,
    StaffUser,
    StoreDep,
    get_current_user,
)
from services.api.downloads import (
    CHECKSUM_HEADER,
    CHECKSUM_RESPONSE,
    FormatQuery,
    model_response,
)
from services.api.plots import curve_png
from services.api.schemas.common import MAX_ROW_ID, NO_NUL_PATTERN, Page
from services.api.schemas.jobs import (
    CurvePublic,
    JobCreate,
    JobLogEntry,
    JobLogPublic,
    JobPublic,
)
from services.api.settings import ApiSettings
from services.core.artifacts import TENSORBOARD_KIND, job_folder
from services.core.db.base import utcnow
from services.core.db.jobs import end_live_runs_of_ended_job
from services.core.db.models import (
    JOB_FINAL_STATUSES,
    AuditEntry,
    Classifier,
    HFModel,
    Job,
    LabSession,
    Recording,
    Subject,
)
from services.core.disk import require_free_space
from services.core.errors import BadRequestError, ConflictError, NotFoundError
from services.core.queue import enqueue_job
from services.platform.jobs import EEG_CALIBRATION, GUIDED_PPO, KindName, job_kind
from services.platform.jobs.resource import JobStatus

log = logging.getLogger(__name__)
router = APIRouter(prefix="/api/v1/jobs", tags=["jobs"])
SIGNED_IN = [Depends(get_current_user)]
"""The sign-in of every jobs route (any role; staff routes ask for more), before any of the
route's parameters is checked: a bad token is a 401 whatever the query says."""


def _validated_config(db: Session, kind: str, config: dict[str, Any]) -> dict[str, Any]:
    """The config checked against its kind's schema, defaults filled in; 422 naming the field."""
    try:
        parsed = job_kind(kind).parse(config)
    except ValidationError as exc:
        errors = []
        for err in exc.errors():
            err = dict(err)
            err["loc"] = ("body", "config", *err.get("loc", ()))
            err.pop("ctx", None)
            errors.append(err)
        raise RequestValidationError(errors) from None
    values = parsed.model_dump(mode="json", exclude_none=True)
    hf_model_id = values.get("hf_model_id") if kind == GUIDED_PPO.name else None
    if hf_model_id is not None and db.get(HFModel, hf_model_id) is None:
        raise BadRequestError(
            f"no HF model with id {values['hf_model_id']}", field="config.hf_model_id"
        )
    for name, model in (("subject_id", Subject), ("session_id", LabSession)):
        if name in values and db.get(model, values[name]) is None:
            raise BadRequestError(f"no {name[:-3]} with id {values[name]}", field=f"config.{name}")
    if (
        values.get("classifier_id") is not None
        and db.get(Classifier, values["classifier_id"]) is None
    ):
        raise BadRequestError(
            f"no classifier with id {values['classifier_id']}", field="config.classifier_id"
        )
    if kind == EEG_CALIBRATION.name:
        recording = db.get(Recording, values["recording_id"])
        if recording is None:
            raise BadRequestError(
                f"no recording with id {values['recording_id']}", field="config.recording_id"
            )
        if recording.validation_status != "valid":
            raise BadRequestError(
                f"recording {recording.id} is {recording.validation_status}, not valid",
                field="config.recording_id",
            )
    return values


def require_job_space(settings: ApiSettings, refusing: str) -> None:
    """507 unless the artifact store's disk (where jobs write) keeps its reserve free."""
    require_free_space(
        settings.resolved_artifact_dir, min_free_mb=settings.min_free_mb, refusing=refusing
    )


def _enqueue(celery: Celery, job: Job) -> None:
    """Send the job to the workers; a broker outage leaves it queued for the reaper."""
    try:
        enqueue_job(celery, job.id, job.kind)
    except Exception as exc:  # the row is committed: the workers' reaper re-sends it
        log.warning("job %s committed but not enqueued (%s: %s)", job.id, type(exc).__name__, exc)


@router.post("", status_code=status.HTTP_201_CREATED, dependencies=SIGNED_IN)
def submit(
    body: JobCreate, user: StaffUser, db: DbDep, celery: CeleryDep, settings: SettingsDep
) -> JobPublic:
    """Submit a job (staff): the row is committed as ``queued``, then sent to the workers.

    Refused with 507 while the data disk keeps less than ``BGRL_MIN_FREE_MB`` free.
    """
    require_job_space(settings, "a new job")
    config = _validated_config(db, body.kind, body.config)
    job = Job(
        kind=body.kind,
        config=config,
        status="queued",
        submitter_id=user.id,
        max_attempts=settings.job_max_attempts,
    )
    db.add(job)
    db.flush()
    audit.record(db, user, "job.submit", "job", job.id, kind=job.kind)
    db.commit()
    _enqueue(celery, job)
    return JobPublic.model_validate(job)


MAX_PARENT_ID_CHARS = 32
"""The longest ``parent_id`` the list takes (a job id is 32 hex digits)."""
JOB_LIST_FILTERS = {
    "status": Job.status,
    "kind": Job.kind,
    "submitter_id": Job.submitter_id,
    "parent_id": Job.parent_id,
}


@functools.cache
def _job_list_query(filters: tuple[str, ...]) -> PageQuery:
    """The job list, newest first, filtered on the columns named (values as parameters):
    :class:`JobPublic`'s columns only (not the curve, up to hundreds of points, nor
    tracebacks)."""
    columns = [Job.__table__.c[name] for name in JobPublic.model_fields]
    query = select(*columns).order_by(Job.created_at.desc(), Job.id)
    for name in filters:
        query = query.where(JOB_LIST_FILTERS[name] == bindparam(name))
    return PageQuery(query)


JOB_PAGE = TypeAdapter(Page[JobPublic])
"""The job list's answer: its rows validated once and written as JSON by pydantic-core."""


@router.get("", response_model=Page[JobPublic], dependencies=SIGNED_IN)
def list_jobs(
    db: DbDep,
    page: PageDep,
    status_: Annotated[JobStatus | None, Query(alias="status")] = None,
    kind: Annotated[KindName | None, Query()] = None,
    submitter_id: Annotated[int | None, Query(ge=1, le=MAX_ROW_ID)] = None,
    parent_id: Annotated[
        str | None, Query(max_length=MAX_PARENT_ID_CHARS, pattern=NO_NUL_PATTERN)
    ] = None,
) -> Response:
    """Jobs, newest first, by status, kind, submitter or parent (a reproduce job's runs).

    Any signed-in user. The page is validated once (:data:`JOB_PAGE`) and sent as its JSON
    bytes, which FastAPI's ``response_model`` path would validate and serialise again; the
    model still documents the answer.
    """
    given = {"status": status_, "kind": kind, "submitter_id": submitter_id, "parent_id": parent_id}
    params = {name: value for name, value in given.items() if value is not None}
    items = _job_list_query(tuple(params)).paginate(db.connection(), page, params)
    body = JOB_PAGE.dump_json(JOB_PAGE.validate_python(items))
    return Response(body, media_type="application/json")


@router.get("/{job_id}", dependencies=SIGNED_IN)
def read(job_id: str, db: DbDep) -> JobPublic:
    """One job: status, progress, attempts, resumed_from_step, error."""
    return JobPublic.model_validate(get_by_id_or_prefix(db, Job, job_id, "job_id"))


AUDIT_EVENTS = {"job.submit": "submitted", "job.cancel": "cancel requested", "job.retry": "retried"}
"""The audit log's actions on a job, as its log names them."""


@router.get("/{job_id}/log", dependencies=SIGNED_IN)
def log_entries(job_id: str, db: DbDep) -> JobLogPublic:
    """The job's events, oldest first: submitted, cancelled and retried (by whom, from the
    audit log), started (with the attempt and the step it resumed from), and how it ended
    (with the error); a reproduction's runs by status."""
    job = get_by_id_or_prefix(db, Job, job_id, "job_id")
    entries = [
        JobLogEntry(
            at=entry.at,
            event=AUDIT_EVENTS.get(entry.action, entry.action),
            detail=", ".join(f"{key} {value}" for key, value in sorted(entry.detail.items())),
            actor_email=entry.actor_email,
        )
        for entry in db.scalars(
            select(AuditEntry).where(
                AuditEntry.target_type == "job", AuditEntry.target_id == job.id
            )
        )
    ]
    if not any(entry.event == "submitted" for entry in entries):
        entries.append(JobLogEntry(at=job.created_at, event="submitted", detail=f"kind {job.kind}"))
    if job.started_at is not None:
        resumed = (
            f", resumed from step {job.resumed_from_step}"
            if job.resumed_from_step is not None
            else ""
        )
        entries.append(
            JobLogEntry(
                at=job.started_at,
                event="started",
                detail=f"attempt {job.attempts} of {job.max_attempts}{resumed}",
            )
        )
    if job.finished_at is not None:
        entries.append(JobLogEntry(at=job.finished_at, event=job.status, detail=job.error or ""))
    runs = db.execute(
        select(Job.status, func.count()).where(Job.parent_id == job.id).group_by(Job.status)
    ).all()
    if runs:
        counts = ", ".join(f"{n} {status}" for status, n in sorted(runs))
        entries.append(JobLogEntry(at=job.updated_at, event="runs", detail=counts))
    entries.sort(key=lambda entry: entry.at)
    return JobLogPublic(job_id=job.id, items=entries)


@router.post("/{job_id}/cancel", dependencies=SIGNED_IN)
def cancel(job_id: str, user: StaffUser, db: DbDep) -> JobPublic:
    """Cancel a job (staff): a queued one at once, a running one within seconds (its worker
    checks on every heartbeat). A reproduce job's runs are cancelled with it. A live
    session's run ends with its rows kept and ``cancelled by <email>`` as its reason."""
    job = get_by_id_or_prefix(db, Job, job_id, "job_id")
    if job.status in JOB_FINAL_STATUSES:
        raise ConflictError(f"job {job.id} is already {job.status}", field="job_id")
    now = utcnow()
    for query in (Job.id == job.id, Job.parent_id == job.id):
        db.execute(
            update(Job)
            .where(query, Job.status == "queued")
            .values(status="cancelled", cancel_requested=True, finished_at=now, updated_at=now)
        )
        db.execute(
            update(Job)
            .where(query, Job.status == "running")
            .values(cancel_requested=True, updated_at=now)
        )
    audit.record(db, user, "job.cancel", "job", job.id)
    db.commit()
    db.refresh(job)
    if job.status == "cancelled":  # it was queued: no worker ends its live run
        end_live_runs_of_ended_job(db, job.id, job.status, None)
        db.refresh(job)
    return JobPublic.model_validate(job)


RETRYABLE = ("failed", "cancelled")
"""The statuses a retry starts again from."""


def _requeue(job_filter: Any) -> Any:
    """The update that puts the retryable jobs ``job_filter`` picks back to ``queued``."""
    return (
        update(Job)
        .where(job_filter, Job.status.in_(RETRYABLE))
        .values(
            status="queued",
            error=None,
            traceback=None,
            cancel_requested=False,
            finished_at=None,
            attempts=0,
            lease_owner=None,
            lease_expires_at=None,
            updated_at=utcnow(),
        )
        .execution_options(synchronize_session=False)
    )


@router.post("/{job_id}/retry", dependencies=SIGNED_IN)
def retry(
    job_id: str, user: StaffUser, db: DbDep, celery: CeleryDep, settings: SettingsDep
) -> JobPublic:
    """Run a failed or cancelled job again (staff); it resumes from its last checkpoint.

    A reproduce job's failed and cancelled runs are run again with it (its finished runs
    are kept). The row changes in one conditional update: of two retries at once, one wins
    (the other gets 409), so the job is sent once. Refused with 507 while the data disk
    keeps less than ``BGRL_MIN_FREE_MB`` free.
    """
    require_job_space(settings, "retrying a job")
    job = get_by_id_or_prefix(db, Job, job_id, "job_id")
    if job.parent_id is not None:
        raise ConflictError(
            f"job {job.id} is a run of job {job.parent_id}; retry that", field="job_id"
        )
    if db.execute(_requeue(Job.id == job.id)).rowcount != 1:
        db.rollback()
        db.refresh(job)
        raise ConflictError(
            f"job {job.id} is {job.status}; only failed or cancelled jobs can be retried",
            field="job_id",
        )
    runs = list(db.scalars(select(Job).where(Job.parent_id == job.id, Job.status.in_(RETRYABLE))))
    if runs:
        db.execute(_requeue(Job.id.in_([run.id for run in runs])))
    audit.record(db, user, "job.retry", "job", job.id, runs=len(runs))
    db.commit()
    db.refresh(job)
    for run in runs:
        _enqueue(celery, run)
    _enqueue(celery, job)
    return JobPublic.model_validate(job)


@router.get(
    "/{job_id}/curve",
    dependencies=SIGNED_IN,
    responses={200: {"content": {"application/json": {}, "text/csv": {}}}},
)
def curve(
    job_id: str,
    db: DbDep,
    curve_format: Annotated[Literal["json", "csv"], Query(alias="format")] = "json",
) -> Any:
    """The learning curve so far: ``[step, SPL]`` pairs (JSON, or CSV with ``format=csv``)."""
    job = get_by_id_or_prefix(db, Job, job_id, "job_id")
    points = [(int(step), float(spl)) for step, spl in job.curve]
    if curve_format == "csv":
        buffer = io.StringIO()
        writer = csv.writer(buffer, lineterminator="\n")
        writer.writerow(["step", "spl"])
        writer.writerows(points)
        return Response(
            buffer.getvalue(),
            media_type="text/csv",
            headers={"Content-Disposition": f'attachment; filename="job-{job.id}-curve.csv"'},
        )
    return CurvePublic(job_id=job.id, curve=points)


@router.get(
    "/{job_id}/plot.png",
    dependencies=SIGNED_IN,
    response_class=Response,
    responses={200: {"content": {"image/png": {}}}},
)
def plot(job_id: str, db: DbDep) -> Response:
    """The learning curve as a PNG."""
    job = get_by_id_or_prefix(db, Job, job_id, "job_id")
    if not job.curve:
        raise NotFoundError(f"job {job.id} has no learning-curve points yet", field="job_id")
    title = f"{job.kind} {job.config.get('task', '')} {job.config.get('method', '')}".strip()
    hf_spl = (job.result or {}).get("hf_policy_spl")
    hf_line = float(hf_spl) if isinstance(hf_spl, int | float) and math.isfinite(hf_spl) else None
    return Response(curve_png(job.curve, title, hf_policy_spl=hf_line), media_type="image/png")


@router.get(
    "/{job_id}/tensorboard",
    dependencies=SIGNED_IN,
    response_class=Response,
    responses={
        200: {
            "content": {"application/zip": {}},
            "headers": {CHECKSUM_HEADER: {"description": "SHA-256 of the zip (hex)."}},
        }
    },
)
def tensorboard(job_id: str, db: DbDep, store: StoreDep) -> Response:
    """The training job's TensorBoard event files as a zip (``job-<id>/events...``), as they
    are now: unzip and run ``tensorboard --logdir`` on the folder. Scalars use CleanRL's
    names (``losses/...``, ``charts/episodic_return``, ``charts/SPL``, ...)."""
    job = get_by_id_or_prefix(db, Job, job_id, "job_id")
    folder = store.path(job_folder(TENSORBOARD_KIND, job.id))
    events = sorted(p for p in folder.glob("events.out.tfevents.*") if p.is_file())
    if not events:
        raise NotFoundError(
            f"job {job.id} ({job.status}) has no TensorBoard events", field="job_id"
        )
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for path in events:
            archive.write(path, f"job-{job.id}/{path.name}")
    data = buffer.getvalue()
    return Response(
        data,
        media_type="application/zip",
        headers={
            "Content-Disposition": f'attachment; filename="job-{job.id}-tensorboard.zip"',
            CHECKSUM_HEADER: hashlib.sha256(data).hexdigest(),
        },
    )


@router.get(
    "/{job_id}/model",
    dependencies=SIGNED_IN,
    response_class=FileResponse,
    responses=CHECKSUM_RESPONSE,
)
def model(
    job_id: str, db: DbDep, store: StoreDep, model_format: FormatQuery = "torchscript"
) -> FileResponse:
    """The trained policy as TorchScript, a torch.export program (pt2) or ONNX, each with its
    observation normalisation, and its checksum."""
    job = get_by_id_or_prefix(db, Job, job_id, "job_id")
    if job.model_artifact_id is None:
        raise NotFoundError(f"job {job.id} ({job.status}) has no model yet", field="job_id")
    ids = {
        "torchscript": job.model_artifact_id,
        "pt2": job.model_pt2_artifact_id,
        "onnx": job.model_onnx_artifact_id,
    }
    return model_response(
        db,
        store,
        ids,
        model_format,
        what=f"job {job.id}",
        field="job_id",
        filename=f"policy-{job.id}",
    )
