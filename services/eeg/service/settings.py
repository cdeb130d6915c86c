"""Settings of the EEG service (environment prefix ``BGRL_EEG_``).

Example: ``BGRL_EEG_PORT=8102 BGRL_EEG_DATA_DIR=/srv/bgrl uvicorn services.eeg.service.app:app``.
``data_dir`` also honours the platform-wide ``BGRL_DATA_DIR``.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import AliasChoices, Field
from pydantic_settings import SettingsConfigDict

from services.core.settings import BaseServiceSettings


class EEGSettings(BaseServiceSettings):
    """Configuration of the EEG HTTP/websocket service."""

    model_config = SettingsConfigDict(env_prefix="BGRL_EEG_", extra="ignore")

    port: int = Field(8002, ge=1, le=65535, description="TCP port of the HTTP server.")
    data_dir: Path = Field(
        Path("var"),
        validation_alias=AliasChoices("BGRL_EEG_DATA_DIR", "BGRL_DATA_DIR", "data_dir"),
        description="Folder below which eeg/ holds recordings, classifiers and jobs.",
    )
    max_training_passes: int = Field(
        300, ge=1, le=10000, description="Upper bound on training passes a job may ask for."
    )
    epoch_wait_s: float = Field(
        2.0,
        gt=0.0,
        le=30.0,
        description="How long classifying a marker waits for its epoch window to be complete.",
    )
    lsl_timeout_s: float = Field(
        5.0, gt=0.0, le=60.0, description="How long to wait for an LSL stream to appear."
    )
    allowed_origins: list[str] = Field(
        default_factory=list,
        description="Extra websocket Origins accepted besides the service's own host (JSON list).",
    )

    @property
    def eeg_dir(self) -> Path:
        """Root of everything the EEG service stores."""
        return self.data_dir / "eeg"
