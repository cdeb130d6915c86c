"""Settings base shared by every service (pydantic-settings, ``BGRL_`` prefix)."""

from __future__ import annotations

from pathlib import Path

from pydantic import AliasChoices, Field
from pydantic_settings import BaseSettings, SettingsConfigDict

ENV_PREFIX = "BGRL_"


class BaseServiceSettings(BaseSettings):
    """Fields every service has. Subclasses set ``model_config`` with their own prefix.

    Values come from the environment (e.g. ``BGRL_SIM_PORT=8101``) and are validated
    when the service starts, so a bad value stops it with a message naming the field.
    """

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="ignore", populate_by_name=True)

    host: str = Field("127.0.0.1", description="Interface the HTTP server binds to.")
    port: int = Field(8000, ge=1, le=65535, description="TCP port of the HTTP server.")
    data_dir: Path = Field(
        Path("var"),
        validation_alias=AliasChoices("BGRL_DATA_DIR"),
        description="Platform-wide folder for kept files (recordings, models, caches); each "
        "service uses its own subfolder. Read from BGRL_DATA_DIR.",
    )
    max_upload_bytes: int = Field(
        512 * 1024 * 1024, gt=0, description="Largest request body accepted, in bytes."
    )

    def ensure_data_dir(self) -> Path:
        """Create ``data_dir`` if needed and return it."""
        self.data_dir.mkdir(parents=True, exist_ok=True)
        return self.data_dir
