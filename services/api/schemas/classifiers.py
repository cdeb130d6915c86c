"""Schemas of ErrP classifiers."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from services.api.schemas.common import PublicModel


class ClassifierPublic(PublicModel):
    """An ErrP classifier with its validation metrics and downloadable formats."""

    id: int
    name: str
    subject_id: int | None
    recording_id: int | None
    job_id: str | None
    onnx_artifact_id: str | None
    torchscript_artifact_id: str | None
    pt2_artifact_id: str | None
    metrics: dict[str, Any]
    created_at: datetime
