"""Artifacts: every stored file (recordings, checkpoints, models, results) and its checksum."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query
from fastapi.responses import FileResponse
from sqlalchemy import select

from services.api.crud import get_or_404, paginate
from services.api.deps import DbDep, PageDep, StoreDep, get_current_user
from services.api.downloads import CHECKSUM_RESPONSE, artifact_response
from services.api.schemas.artifacts import ArtifactPublic
from services.api.schemas.common import NO_NUL_PATTERN, Page
from services.core.db.models import Artifact

router = APIRouter(
    prefix="/api/v1/artifacts", tags=["artifacts"], dependencies=[Depends(get_current_user)]
)


@router.get("")
def list_artifacts(
    db: DbDep,
    page: PageDep,
    kind: Annotated[str | None, Query(max_length=32, pattern=NO_NUL_PATTERN)] = None,
    job_id: Annotated[str | None, Query(max_length=32, pattern=NO_NUL_PATTERN)] = None,
) -> Page[ArtifactPublic]:
    """Stored files, newest first, by kind or job."""
    query = select(Artifact).order_by(Artifact.created_at.desc(), Artifact.id)
    if kind is not None:
        query = query.where(Artifact.kind == kind)
    if job_id is not None:
        query = query.where(Artifact.job_id == job_id)
    return Page[ArtifactPublic].model_validate(paginate(db, query, page))


@router.get("/{artifact_id}")
def read(artifact_id: str, db: DbDep) -> ArtifactPublic:
    """One stored file's record."""
    return ArtifactPublic.model_validate(get_or_404(db, Artifact, artifact_id, "artifact_id"))


@router.get("/{artifact_id}/download", response_class=FileResponse, responses=CHECKSUM_RESPONSE)
def download(artifact_id: str, db: DbDep, store: StoreDep) -> FileResponse:
    """The file, with its SHA-256 in ``X-Checksum-Sha256``."""
    artifact = get_or_404(db, Artifact, artifact_id, "artifact_id")
    return artifact_response(store, artifact, artifact.relpath.rsplit("/", 1)[-1])
