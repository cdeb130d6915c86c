"""``bids_export``: a subject's sessions as a BIDS dataset (a zip artifact of kind ``bids``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pydantic import Field

from services.core.schemas import MAX_ROW_ID
from services.platform.jobs.kind import JobConfig, JobKind, form_hints


class BIDSExportConfig(JobConfig):
    """Export a subject's sessions as a BIDS dataset (a zip artifact of kind ``bids``)."""

    subject_id: int = Field(
        ge=1, le=MAX_ROW_ID, title="Subject", json_schema_extra=form_hints(references="subjects")
    )


def summary(config: Mapping[str, Any]) -> str:
    """``BIDS export of subject #3``."""
    return f"BIDS export of subject #{config.get('subject_id')}"


KIND = JobKind(name="bids_export", title="BIDS export", config=BIDSExportConfig, summary=summary)
