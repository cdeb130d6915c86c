"""Settings of the learner service (environment prefix ``BGRL_LEARNER_``).

Example: ``BGRL_LEARNER_PORT=8103 uvicorn services.learner.service.app:app``. Every value is
validated when the service starts; a bad one stops it with a message that names the field.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from services.core.settings import BaseServiceSettings


class LearnerSettings(BaseServiceSettings):
    """Configuration of the learner HTTP service."""

    model_config = SettingsConfigDict(env_prefix="BGRL_LEARNER_", extra="ignore")

    port: int = Field(8003, ge=1, le=65535, description="TCP port of the HTTP server.")
    max_upload_bytes: int = Field(
        64 * 1024,
        gt=0,
        description="Largest request body accepted, in bytes (the service takes only small JSON).",
    )
    max_sessions: int = Field(
        256, ge=1, le=100_000, description="Most HF sessions kept (open or done) at once."
    )
    max_label_budget: int = Field(
        100_000,
        ge=1,
        le=100_000,
        description="Largest label_budget a session may ask for (the feedback buffer holds "
        "at most 100000 labels).",
    )
    checkpoint_every: int = Field(
        100,
        ge=1,
        le=200_000,
        description="Journal entries (labels and sampled actions: a label with its next "
        "action is two) between two full checkpoints of a session (``state.pt``); a restart "
        "replays at most this many.",
    )
    extra_map_dirs: list[Path] = Field(
        default_factory=list,
        description="Folders of user map files sessions may name, besides the shipped maps "
        "(JSON list of paths; give the sim service the same folders).",
    )

    @property
    def sessions_dir(self) -> Path:
        """Where sessions are checkpointed: ``<data_dir>/learner/sessions``."""
        return self.data_dir / "learner" / "sessions"
