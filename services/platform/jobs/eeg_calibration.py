"""``eeg_calibration``: train an ErrP classifier on a stored, valid recording."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pydantic import Field

from services.core.schemas import MAX_ROW_ID
from services.platform.jobs.kind import JobConfig, JobKind, form_hints
from services.platform.jobs.ppo import MAX_SEED


class EEGCalibrationConfig(JobConfig):
    """Train an ErrP classifier on a stored, valid recording."""

    recording_id: int = Field(
        ge=1,
        le=MAX_ROW_ID,
        title="Recording",
        description="A recording the EEG service found valid.",
        json_schema_extra=form_hints(references="recordings"),
    )
    seed: int = Field(0, ge=0, le=MAX_SEED, title="Seed")
    max_passes: int | None = Field(
        None,
        ge=1,
        le=10_000,
        title="Training passes",
        description="Default: the pipeline's.",
    )
    onnx: bool = Field(True, title="ONNX", description="Also export the classifier as ONNX.")
    report: bool = Field(True, title="Report", description="Also write the calibration report.")


def summary(config: Mapping[str, Any]) -> str:
    """``recording #12, seed 0``."""
    return f"recording #{config.get('recording_id')}, seed {config.get('seed', 0)}"


KIND = JobKind(
    name="eeg_calibration", title="EEG calibration", config=EEGCalibrationConfig, summary=summary
)
