"""Settings base shared by every service (pydantic-settings, ``BGRL_`` prefix)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal, TypeVar

from pydantic import AliasChoices, Field, ValidationError
from pydantic_settings import BaseSettings, SettingsConfigDict

from services.core.files import private_folder

ENV_PREFIX = "BGRL_"

SettingsT = TypeVar("SettingsT", bound=BaseSettings)


class SettingsError(ValueError):
    """A setting from the environment is invalid; the message is one line naming it."""


def load_settings(cls: type[SettingsT], **overrides: object) -> SettingsT:
    """``cls(**overrides)`` with a validation failure as one :class:`SettingsError` line.

    The line names the environment variable (e.g. ``BGRL_SIM_PORT``), the value given and
    what is wrong with it, so a bad setting stops a service before it claims to listen.
    """
    try:
        return cls(**overrides)
    except ValidationError as exc:
        prefix = cls.model_config.get("env_prefix", ENV_PREFIX)
        problems = []
        for err in exc.errors():
            field = ".".join(str(p) for p in err["loc"]) or "?"
            given = err.get("input")
            shown = f" (got {given!r})" if isinstance(given, str | int | float) else ""
            problems.append(f"{prefix}{field.upper()}{shown}: {err['msg']}")
        raise SettingsError("invalid setting: " + "; ".join(problems)) from None


class BaseServiceSettings(BaseSettings):
    """Fields every service has. Subclasses set ``model_config`` with their own prefix.

    Values come from the environment (e.g. ``BGRL_SIM_PORT=8101``) and are validated
    when the service starts, so a bad value stops it with a message naming the field.
    """

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="ignore", populate_by_name=True)

    host: str = Field("127.0.0.1", description="Interface the HTTP server binds to.")
    port: int = Field(8000, ge=1, le=65535, description="TCP port of the HTTP server.")
    data_dir: Path = Field(
        Path("data"),
        validation_alias=AliasChoices("BGRL_DATA_DIR"),
        description="Platform-wide folder for kept files (recordings, models, caches); each "
        "service uses its own subfolder. Read from BGRL_DATA_DIR.",
    )
    max_upload_bytes: int = Field(
        512 * 1024 * 1024, gt=0, description="Largest request body accepted, in bytes."
    )
    min_free_mb: int = Field(
        1024,
        ge=0,
        validation_alias=AliasChoices("BGRL_MIN_FREE_MB", "min_free_mb"),
        description="Free space (MB) kept on the data disk: below it, recording uploads and "
        "new jobs are refused with HTTP 507 (platform-wide BGRL_MIN_FREE_MB; 0 turns the "
        "check off). Running jobs, checkpoints and the database still write into it.",
    )
    service_token: str | None = Field(
        None,
        min_length=16,
        validation_alias=AliasChoices("BGRL_SERVICE_TOKEN", "service_token"),
        description="Internal token the platform's services exchange (platform-wide "
        "BGRL_SERVICE_TOKEN). When set, every route but /health requires it in the "
        "X-Service-Token header; the sim, EEG and learner services have no user auth of "
        "their own, so they listen on loopback and take calls only from the platform.",
    )
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field(
        "INFO",
        validation_alias=AliasChoices("BGRL_LOG_LEVEL", "log_level"),
        description="Level of the service's log (platform-wide BGRL_LOG_LEVEL).",
    )
    log_json: bool = Field(
        False,
        validation_alias=AliasChoices("BGRL_LOG_JSON", "log_json"),
        description="Log one JSON object per line instead of text (platform-wide BGRL_LOG_JSON).",
    )
    log_dir: Path | None = Field(
        None,
        validation_alias=AliasChoices("BGRL_LOG_DIR", "log_dir"),
        description="Folder for log files besides stderr: <name>.log per service (api, sim, "
        "eeg, learner, worker, up), rotated by size (platform-wide BGRL_LOG_DIR). Unset: "
        "stderr only (under systemd, journald keeps and rotates it).",
    )
    log_max_mb: int = Field(
        50,
        ge=1,
        le=100_000,
        validation_alias=AliasChoices("BGRL_LOG_MAX_MB", "log_max_mb"),
        description="Size (MB) at which a log file in BGRL_LOG_DIR is rotated.",
    )
    log_backups: int = Field(
        5,
        ge=1,
        le=1000,
        validation_alias=AliasChoices("BGRL_LOG_BACKUPS", "log_backups"),
        description="Rotated log files kept per service (<name>.log.1 ... .N; older ones "
        "are deleted).",
    )

    def ensure_data_dir(self) -> Path:
        """Create ``data_dir`` if needed (mode 700: only its owner may read the data) and
        return it."""
        return private_folder(self.data_dir)
