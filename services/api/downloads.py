"""Files of the artifact store sent with their checksum (``X-Checksum-Sha256``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated

from fastapi import Query
from fastapi.responses import FileResponse
from sqlalchemy.orm import Session

from services.core.artifacts import ArtifactStore
from services.core.db.models import Artifact
from services.core.errors import GoneError, NotFoundError
from services.core.model_formats import SUFFIXES, ModelFormat

FormatQuery = Annotated[
    ModelFormat,
    Query(
        alias="format",
        description="torchscript (torch.jit.load), pt2 (torch.export.load) or onnx; each holds "
        "the observation normalisation (a classifier: its input scaling).",
    ),
]

CHECKSUM_HEADER = "X-Checksum-Sha256"
CHECKSUM_RESPONSE = {
    200: {
        "content": {"application/octet-stream": {}},
        "headers": {CHECKSUM_HEADER: {"description": "SHA-256 of the file (hex)."}},
    }
}


def artifact_response(store: ArtifactStore, artifact: Artifact, filename: str) -> FileResponse:
    """The artifact's file as an attachment named ``filename``; 410 if the file is gone."""
    path = store.path(artifact.relpath)
    if not path.is_file():
        raise GoneError(f"the file of artifact {artifact.id} is missing from the store")
    return FileResponse(
        path,
        media_type="application/octet-stream",
        filename=filename,
        headers={CHECKSUM_HEADER: artifact.sha256},
    )


def model_response(
    db: Session,
    store: ArtifactStore,
    artifact_ids: Mapping[ModelFormat, str | None],
    model_format: ModelFormat,
    *,
    what: str,
    field: str,
    filename: str,
) -> FileResponse:
    """The file of a model in ``model_format`` (its artifact id in ``artifact_ids``), named
    ``filename`` plus the format's ending; 404 naming the format if the model lacks it."""
    artifact_id = artifact_ids.get(model_format)
    if artifact_id is None:
        raise NotFoundError(f"{what} has no {model_format} file", field="format")
    artifact = db.get(Artifact, artifact_id)
    if artifact is None:
        raise NotFoundError(f"the {model_format} file of {what} is gone", field=field)
    return artifact_response(store, artifact, filename + SUFFIXES[model_format])
