"""Settings of a job worker (``BGRL_`` environment variables on top of the platform's)."""

from __future__ import annotations

import os
import socket
from pathlib import Path

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from services.core.platform import PlatformSettings
from services.core.settings import ENV_PREFIX


class WorkerSettings(PlatformSettings):
    """What one worker process needs: the platform's database, broker and artifact store,
    plus how it runs jobs. A worker on another host needs only ``BGRL_DATABASE_URL``,
    ``BGRL_BROKER_URL`` and ``BGRL_ARTIFACT_DIR`` (a shared path)."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="ignore", populate_by_name=True)

    worker_name: str | None = Field(
        None,
        max_length=100,
        description="Name of this worker in leases and logs; default <host>-<pid>.",
    )
    worker_torch_threads: int = Field(
        1,
        ge=1,
        le=64,
        description="Torch threads per worker (1: results do not depend on the thread count, "
        "and N workers share N cores).",
    )
    checkpoint_every: int = Field(
        10, ge=1, description="PPO updates between checkpoints of a training job."
    )
    ready_file: Path | None = Field(
        None,
        description="Set by `bgrl up`: a file the worker creates once it takes jobs (the "
        "supervisor waits for it before calling the platform up).",
    )

    @property
    def owner_name(self) -> str:
        """The lease owner id of this process (unique per process)."""
        base = self.worker_name or socket.gethostname()
        return f"{base}-{os.getpid()}"
