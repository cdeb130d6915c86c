"""Artifacts: every stored file (recordings, checkpoints, models, results) and its checksum."""

from __future__ import annotations

import hashlib
from typing import Annotated

from fastapi import APIRouter, Depends, Query, Response
from fastapi.responses import FileResponse
from sqlalchemy import select

from services.api.crud import get_by_id_or_prefix, paginate
from services.api.deps import DbDep, PageDep, StoreDep, get_current_user
from services.api.downloads import CHECKSUM_HEADER, CHECKSUM_RESPONSE, artifact_response
from services.api.schemas.artifacts import ArtifactPublic
from services.api.schemas.common import NO_NUL_PATTERN, Page
from services.core.artifacts import ArtifactStore
from services.core.db.models import Artifact
from services.core.errors import GoneError

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
    return ArtifactPublic.model_validate(
        get_by_id_or_prefix(db, Artifact, artifact_id, "artifact_id")
    )


REWRITTEN_KINDS = frozenset({"checkpoint"})
"""Kinds of artifact whose file its running job rewrites (atomically, by rename): the row's
checksum is refreshed only at the job's next heartbeat, so such a file is sent with the
checksum of the very bytes sent."""


@router.get("/{artifact_id}/download", response_class=FileResponse, responses=CHECKSUM_RESPONSE)
def download(artifact_id: str, db: DbDep, store: StoreDep) -> Response:
    """The file, with its SHA-256 in ``X-Checksum-Sha256``; 410 if the file is gone."""
    artifact = get_by_id_or_prefix(db, Artifact, artifact_id, "artifact_id")
    filename = artifact.relpath.rsplit("/", 1)[-1]
    if artifact.kind in REWRITTEN_KINDS:
        return _current_file(store, artifact, filename)
    return artifact_response(store, artifact, filename)


def _current_file(store: ArtifactStore, artifact: Artifact, filename: str) -> Response:
    """The file as it is now, read at one open (one version of it) and hashed as sent."""
    try:
        data = store.path(artifact.relpath).read_bytes()
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
        raise GoneError(f"the file of artifact {artifact.id} is missing from the store") from None
    return Response(
        data,
        media_type="application/octet-stream",
        headers={
            CHECKSUM_HEADER: hashlib.sha256(data).hexdigest(),
            "Content-Disposition": f'attachment; filename="{filename}"',
        },
    )
