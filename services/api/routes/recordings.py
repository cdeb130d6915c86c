"""Recordings: streamed upload (checksum computed on the way), validation, download."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse
from sqlalchemy import select

from services.api import audit
from services.api.crud import busy_job, get_or_404, paginate
from services.api.deps import (
    AdminUser,
    DbDep,
    PageDep,
    RowId,
    SettingsDep,
    StaffUser,
    StoreDep,
    get_current_user,
)
from services.api.downloads import CHECKSUM_RESPONSE, artifact_response
from services.api.eeg_client import validate_recording
from services.api.schemas.common import MAX_ROW_ID, Page
from services.api.schemas.recordings import RecordingPublic, ValidationStatus
from services.api.uploads import receive_recording
from services.core.artifacts import ArtifactStore, StoredFile
from services.core.db.base import utcnow
from services.core.db.models import Artifact, LabSession, Recording, User
from services.core.errors import ConflictError, NotFoundError

router = APIRouter(tags=["recordings"], dependencies=[Depends(get_current_user)])


def _apply_validation(
    request: Request, db: DbDep, store: ArtifactStore, recording: Recording
) -> None:
    """Ask the EEG service about the recording's file and store its verdict on the row."""
    settings = request.app.state.settings
    artifact = db.get(Artifact, recording.artifact_id)
    assert artifact is not None
    result = validate_recording(
        store.path(artifact.relpath),
        recording.filename,
        eeg_url=settings.eeg_url,
        timeout_s=settings.eeg_timeout_s,
        service_token=settings.service_token,
    )
    recording.validation_status = result.status
    recording.validation_reason = result.reason
    if result.status != "pending":
        recording.validated_at = utcnow()
    if result.status == "valid":
        recording.synthetic = result.synthetic
        recording.n_channels = result.n_channels
        recording.sfreq = result.sfreq
        recording.duration_s = result.duration_s


def _register(
    request: Request,
    store: ArtifactStore,
    session_id: int,
    stored: StoredFile,
    name: str,
    user: User,
) -> RecordingPublic:
    with request.app.state.sessions() as db:
        artifact = Artifact(
            kind="recording",
            relpath=stored.relpath,
            sha256=stored.sha256,
            size_bytes=stored.size_bytes,
            owner_id=user.id,
        )
        db.add(artifact)
        db.flush()
        recording = Recording(
            session_id=session_id,
            artifact_id=artifact.id,
            filename=name,
            sha256=stored.sha256,
            size_bytes=stored.size_bytes,
            validation_status="pending",
            uploaded_by_id=user.id,
        )
        db.add(recording)
        db.flush()
        audit.record(db, user, "recording.upload", "recording", recording.id, sha256=stored.sha256)
        db.commit()
        _apply_validation(request, db, store, recording)
        db.commit()
        return RecordingPublic.model_validate(recording)


@router.post(
    "/api/v1/sessions/{session_id}/recordings",
    status_code=status.HTTP_201_CREATED,
    openapi_extra={
        "requestBody": {
            "content": {
                "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
                "multipart/form-data": {
                    "schema": {
                        "type": "object",
                        "properties": {"file": {"type": "string", "format": "binary"}},
                        "required": ["file"],
                    }
                },
            }
        }
    },
)
async def upload(
    session_id: RowId,
    request: Request,
    user: StaffUser,
    settings: SettingsDep,
    store: StoreDep,
    filename: Annotated[
        str | None,
        Query(
            max_length=255,
            description="File name (.bdf, .edf, .fif, .set, .xdf, or .zip for a BrainVision "
            "set or an EEGLAB .set with its .fdt); "
            "needed with a raw body.",
        ),
    ] = None,
) -> RecordingPublic:
    """Upload a recording of a session (staff): multipart ``file`` or the raw bytes.

    The SHA-256 is computed while the file streams in; the EEG pipeline then validates it
    and the verdict (``validation_status``, ``validation_reason``, ``synthetic``) is stored.
    """

    def session_exists() -> bool:
        with request.app.state.sessions() as db:
            return db.get(LabSession, session_id) is not None

    if not await run_in_threadpool(session_exists):
        raise NotFoundError(f"no session with id {session_id}", field="session_id")
    stored, name = await receive_recording(
        request,
        store,
        filename=filename,
        max_bytes=settings.max_upload_bytes,
        min_free_mb=settings.min_free_mb,
    )
    try:
        return await run_in_threadpool(_register, request, store, session_id, stored, name, user)
    except BaseException:
        store.delete(stored.relpath)
        raise


@router.get("/api/v1/recordings")
def list_recordings(
    db: DbDep,
    page: PageDep,
    session_id: Annotated[int | None, Query(ge=1, le=MAX_ROW_ID)] = None,
    subject_id: Annotated[int | None, Query(ge=1, le=MAX_ROW_ID)] = None,
    validation_status: Annotated[ValidationStatus | None, Query()] = None,
) -> Page[RecordingPublic]:
    """Recordings, newest first, by session, subject or validation status."""
    query = select(Recording).order_by(Recording.id.desc())
    if session_id is not None:
        query = query.where(Recording.session_id == session_id)
    if subject_id is not None:
        query = query.join(LabSession, Recording.session_id == LabSession.id).where(
            LabSession.subject_id == subject_id
        )
    if validation_status is not None:
        query = query.where(Recording.validation_status == validation_status)
    return Page[RecordingPublic].model_validate(paginate(db, query, page))


@router.get("/api/v1/recordings/{recording_id}")
def read(recording_id: RowId, db: DbDep) -> RecordingPublic:
    """One recording."""
    return RecordingPublic.model_validate(get_or_404(db, Recording, recording_id, "recording_id"))


@router.get(
    "/api/v1/recordings/{recording_id}/file",
    response_class=FileResponse,
    responses=CHECKSUM_RESPONSE,
)
def download(recording_id: RowId, db: DbDep, store: StoreDep) -> FileResponse:
    """The recording's file, with its SHA-256 in ``X-Checksum-Sha256``."""
    recording = get_or_404(db, Recording, recording_id, "recording_id")
    artifact = get_or_404(db, Artifact, recording.artifact_id, "recording_id")
    return artifact_response(store, artifact, recording.filename)


@router.post("/api/v1/recordings/{recording_id}/validate")
def revalidate(
    recording_id: RowId, request: Request, user: StaffUser, db: DbDep, store: StoreDep
) -> RecordingPublic:
    """Ask the EEG pipeline again (e.g. after it was unreachable) (staff)."""
    recording = get_or_404(db, Recording, recording_id, "recording_id")
    _apply_validation(request, db, store, recording)
    audit.record(
        db,
        user,
        "recording.validate",
        "recording",
        recording.id,
        status=recording.validation_status,
    )
    db.commit()
    return RecordingPublic.model_validate(recording)


@router.delete("/api/v1/recordings/{recording_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete(recording_id: RowId, admin: AdminUser, db: DbDep, store: StoreDep) -> None:
    """Delete a recording and its file (admin, audited); 409 while a queued or running
    calibration job trains on it."""
    recording = get_or_404(db, Recording, recording_id, "recording_id")
    job = busy_job(db, recording_ids={recording_id})
    if job is not None:
        raise ConflictError(
            f"{job.kind} job {job.id} ({job.status}) uses recording {recording_id}; "
            "cancel it first",
            field="recording_id",
        )
    artifact = db.get(Artifact, recording.artifact_id)
    db.delete(recording)
    db.flush()
    if artifact is not None:
        db.delete(artifact)
    audit.record(db, admin, "recording.delete", "recording", recording_id, sha256=recording.sha256)
    db.commit()
    if artifact is not None:
        store.delete(artifact.relpath)
