"""Settings of the sim service (environment prefix ``BGRL_SIM_``).

Example: ``BGRL_SIM_PORT=8101 BGRL_SIM_FRAME_RATE_FPS=10 uvicorn services.sim.app:app``.
Every value is validated when the service starts; a bad one stops it with a message that
names the field.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from services.core.actions import ACTION_PERIOD_S
from services.core.settings import BaseServiceSettings


class SimSettings(BaseServiceSettings):
    """Configuration of the sim HTTP/websocket service."""

    model_config = SettingsConfigDict(env_prefix="BGRL_SIM_", extra="ignore")

    port: int = Field(8001, ge=1, le=65535, description="TCP port of the HTTP server.")
    max_upload_bytes: int = Field(
        64 * 1024,
        gt=0,
        description="Largest request body accepted, in bytes (the sim takes only small JSON).",
    )
    frame_rate_fps: float = Field(
        5.0, ge=1.0, le=30.0, description="Default rate of the websocket frame stream (1-30 fps)."
    )
    frame_width: int = Field(320, ge=32, le=1920, description="Width of streamed frames (px).")
    frame_height: int = Field(240, ge=24, le=1080, description="Height of streamed frames (px).")
    jpeg_quality: int = Field(80, ge=10, le=95, description="JPEG quality of streamed frames.")
    paced_action_period_s: float = Field(
        ACTION_PERIOD_S,
        ge=0.05,
        le=60.0,
        description="Default period of the paced mode: one action every this many seconds.",
    )
    max_sessions: int = Field(8, ge=1, le=256, description="Most sim sessions open at once.")
    session_idle_timeout_s: float = Field(
        3600.0,
        ge=1.0,
        description="A session unused this long (no request, step, streamed frame or paced "
        "mode) is closed when another session is opened.",
    )
    max_queued_actions: int = Field(
        1000, ge=1, description="Most actions a client may queue for the paced mode."
    )
    lsl_markers: bool = Field(
        True, description="Publish one LSL marker per executed action (stream BrainNav-Markers)."
    )
    marker_source_id: str | None = Field(
        None,
        min_length=1,
        max_length=200,
        description="LSL source_id of the marker stream (default bgrl-sim@<host>:<port>); "
        "recorders use it to re-attach after a restart.",
    )
    allowed_origins: list[str] = Field(
        default_factory=list,
        description=(
            "Extra websocket Origins accepted besides the service's own host "
            '(JSON list, e.g. ["http://localhost:5173"]).'
        ),
    )
    extra_map_dirs: list[Path] = Field(
        default_factory=list,
        description=(
            "Folders of user map files that sessions may load, besides the shipped maps "
            "(JSON list of paths). Clients can name no other file."
        ),
    )

    @property
    def oracle_cache_dir(self) -> Path:
        """Where oracle lattices are cached on disk: ``<data_dir>/sim/oracle``."""
        return self.data_dir / "sim" / "oracle"
