"""Files of the artifact store sent with their checksum (``X-Checksum-Sha256``)."""

from __future__ import annotations

from fastapi.responses import FileResponse

from services.core.artifacts import ArtifactStore
from services.core.db.models import Artifact
from services.core.errors import GoneError

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
