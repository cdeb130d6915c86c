"""Schemas of artifacts (files in the artifact store)."""

from __future__ import annotations

from datetime import datetime

from services.api.schemas.common import PublicModel


class ArtifactPublic(PublicModel):
    """A stored file and its checksum."""

    id: str
    kind: str
    relpath: str
    sha256: str
    size_bytes: int
    owner_id: int | None
    job_id: str | None
    created_at: datetime
