"""Settings shared by the platform's api and workers: database, broker, artifact store, jobs."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from services.core.settings import ENV_PREFIX, BaseServiceSettings


class PlatformSettings(BaseServiceSettings):
    """What the api and every worker must agree on (``BGRL_`` environment variables).

    A worker on another host needs only ``BGRL_DATABASE_URL``, ``BGRL_BROKER_URL`` and a
    shared ``BGRL_ARTIFACT_DIR`` to take jobs. ``service_token`` (``BGRL_SERVICE_TOKEN``,
    from :class:`BaseServiceSettings`) is what the platform sends to the sim and EEG services.
    """

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="ignore", populate_by_name=True)

    database_url: str | None = Field(
        None,
        description="SQLAlchemy URL of the platform database (e.g. "
        "postgresql+psycopg://user@host/db); default: the SQLite file <data_dir>/bgrl.db.",
    )
    broker_url: str | None = Field(
        None,
        description="Celery broker URL (e.g. redis://host:6379/0); default: an embedded "
        "filesystem broker under <data_dir>/broker that needs no server.",
    )
    artifact_dir: Path | None = Field(
        None,
        description="Root of the artifact store (recordings, checkpoints, models); a path "
        "shared by every host running a worker. Default: <data_dir>/artifacts.",
    )
    workers: int = Field(1, ge=1, le=64, description="Worker processes `bgrl up` starts.")
    job_lease_s: float = Field(
        30.0, gt=0, description="Seconds a worker's claim on a job lasts without a heartbeat."
    )
    job_heartbeat_s: float = Field(
        5.0, gt=0, description="Seconds between a running job's heartbeats (and cancel checks)."
    )
    job_max_attempts: int = Field(
        3, ge=1, le=100, description="Attempts a job gets before it is marked failed."
    )
    reaper_interval_s: float = Field(
        2.0, gt=0, description="Seconds between passes of the reaper of expired leases."
    )
    stale_queued_s: float = Field(
        900.0,
        gt=0,
        description="A job queued this long without being claimed is sent again (its message "
        "may have died with a worker); duplicates are dropped.",
    )

    @property
    def resolved_database_url(self) -> str:
        """``database_url``, or the SQLite file ``<data_dir>/bgrl.db`` (absolute path)."""
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'bgrl.db').resolve()}"

    @property
    def resolved_artifact_dir(self) -> Path:
        """``artifact_dir``, or ``<data_dir>/artifacts`` (absolute path)."""
        root = self.artifact_dir if self.artifact_dir is not None else self.data_dir / "artifacts"
        return root.resolve()
