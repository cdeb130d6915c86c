"""Recordings: upload (multipart or raw bytes), list, inspect."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request, status
from fastapi.responses import JSONResponse

from services.eeg.service.deps import RecordingsDep, SettingsDep
from services.eeg.service.schemas import RecordingPublic
from services.eeg.service.uploads import UPLOAD_OPENAPI, receive_upload

router = APIRouter(prefix="/recordings", tags=["recordings"])


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=RecordingPublic,
    openapi_extra=UPLOAD_OPENAPI,
    responses={
        200: {"model": RecordingPublic, "description": "Already stored (same sha256)."},
        413: {"description": "Larger than BGRL_EEG_MAX_UPLOAD_BYTES."},
        415: {"description": "Not a BDF, EDF, FIF, BrainVision (zip) or XDF file (by content)."},
        422: {"description": "Not a usable recording; the detail names the problem."},
        507: {"description": "The data disk would keep less than BGRL_MIN_FREE_MB free."},
    },
)
async def upload_recording(
    request: Request,
    recordings: RecordingsDep,
    settings: SettingsDep,
    filename: Annotated[
        str | None,
        Query(
            min_length=1,
            max_length=200,
            description="Name to keep with a raw-bytes upload (a label: the format is "
            "detected from the file's header).",
        ),
    ] = None,
) -> RecordingPublic | JSONResponse:
    """Validate and store a BDF/EDF/FIF/BrainVision (zip)/XDF recording under its sha256.

    Send a multipart form with the file in the field ``file``, or the file's bytes as the
    body. 201 when stored, 200 when the same file is already stored.
    """
    upload = await receive_upload(
        request,
        recordings.incoming,
        filename=filename,
        max_bytes=settings.max_upload_bytes,
        min_free_mb=settings.min_free_mb,
    )
    meta, created = await recordings.add(upload)
    if not created:
        return JSONResponse(meta.model_dump(mode="json"), status_code=status.HTTP_200_OK)
    return meta


@router.get("")
def list_recordings(recordings: RecordingsDep) -> list[RecordingPublic]:
    """Every stored recording."""
    return recordings.list()


@router.get("/{recording_id}")
def read_recording(recording_id: str, recordings: RecordingsDep) -> RecordingPublic:
    """One stored recording."""
    return recordings.get(recording_id)
