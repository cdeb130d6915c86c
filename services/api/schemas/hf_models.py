"""Schemas of human-feedback policies (pi_HF)."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from services.api.schemas.common import PublicModel


class HFModelPublic(PublicModel):
    """A human-feedback policy with its metrics and downloadable formats."""

    id: int
    name: str
    task: str
    feedback_accuracy: float | None
    n_labels: int | None
    session_id: int | None
    job_id: str | None
    torchscript_artifact_id: str | None
    onnx_artifact_id: str | None
    pt2_artifact_id: str | None
    metrics: dict[str, Any]
    created_at: datetime
