"""Settings of the api service (``BGRL_`` environment variables, on top of the platform's).

Example: ``BGRL_DATABASE_URL=postgresql+psycopg://bgrl@db/bgrl BGRL_ADMIN_EMAIL=a@lab.org
BGRL_ADMIN_PASSWORD=... uvicorn services.api.app:app --port 8000``.
"""

from __future__ import annotations

import ipaddress
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import Field, SecretStr, field_validator

from services.core.platform import PlatformSettings

MAX_DEFAULT_API_WORKERS = 4


def default_api_workers(settings: Mapping[str, Any]) -> int:
    """One api process per CPU core, at most ``MAX_DEFAULT_API_WORKERS``, on PostgreSQL;
    one on SQLite (the embedded default, one host), where the processes would share one
    file's locks and each holds its own ~150 MiB; one carries the job list at 200 req/s
    (~0.4 of a core) and two measured worse on 2 cores (docs/benchmarks.md, api)."""
    url = settings.get("database_url")
    if not url or str(url).startswith("sqlite"):
        return 1
    return max(1, min(MAX_DEFAULT_API_WORKERS, os.cpu_count() or 1))


class ApiSettings(PlatformSettings):
    """Configuration of the api (everything the platform shares, plus auth and limits)."""

    port: int = Field(8000, ge=1, le=65535, description="TCP port of the HTTP server.")
    api_workers: int = Field(
        default_factory=default_api_workers,
        ge=1,
        le=64,
        description="Api processes `bgrl up` starts behind the one port (uvicorn --workers); "
        "default: one on SQLite, one per CPU core (at most 4) on PostgreSQL.",
    )
    max_upload_bytes: int = Field(
        1024 * 1024 * 1024,
        gt=0,
        description="Largest recording upload accepted, in bytes (other requests: "
        "max_request_bytes).",
    )
    max_request_bytes: int = Field(
        1024 * 1024, gt=0, description="Largest request body of every route but uploads."
    )
    jwt_secret: SecretStr | None = Field(
        None,
        min_length=32,
        description="Key signing access tokens (HS256). Default: a random key generated once "
        "and kept in <data_dir>/api/jwt.key (mode 600).",
    )
    access_token_minutes: int = Field(
        30, ge=1, le=24 * 60, description="Lifetime of an access token from the login route."
    )
    admin_email: str | None = Field(
        None, description="E-mail of the admin created at first start if there is no user."
    )
    admin_password: SecretStr | None = Field(
        None,
        min_length=12,
        description="Password of that admin; without it, first start generates one and "
        "prints it once.",
    )
    login_max_failures: int = Field(
        5, ge=1, le=1000, description="Failed logins allowed per account and client address..."
    )
    login_window_s: float = Field(
        300.0, gt=0, description="...within this many seconds; more are refused with 429."
    )
    database_connections: int = Field(
        15,
        ge=1,
        le=200,
        description="Database connections each api process keeps (opened when first "
        "needed); requests beyond them wait for one.",
    )
    eeg_url: str | None = Field(
        "http://127.0.0.1:8002",
        description="Base URL of the EEG service that validates uploaded recordings (empty: "
        "recordings stay pending).",
    )
    sim_url: str | None = Field(
        "http://127.0.0.1:8001",
        description="Base URL of the sim service whose frames the live pages relay (empty: "
        "no frames).",
    )
    eeg_timeout_s: float = Field(
        120.0, gt=0, le=3600, description="How long a recording's validation may take."
    )
    allowed_origins: list[str] = Field(
        default_factory=list,
        description="Extra websocket Origins accepted besides the api's own host (JSON list).",
    )
    supervisor_status_file: Path | None = Field(
        None,
        description="Set by `bgrl up`: the JSON file where it keeps the state of the "
        "processes it supervises; /readyz reports it.",
    )
    trusted_proxies: list[str] = Field(
        default_factory=list,
        description="Addresses or networks of the reverse proxies in front of the api (JSON "
        'list, e.g. ["10.0.0.5", "10.1.0.0/16"]) whose X-Forwarded-For and '
        "X-Forwarded-Proto are believed. Default: none, not even loopback; a client's "
        "address (what the failed-login limit counts by, and what the log shows) is the "
        "TCP peer's.",
    )
    migrate_on_start: bool = Field(
        True, description="Run the database migrations when the api starts."
    )

    @field_validator("trusted_proxies")
    @classmethod
    def _addresses(cls, entries: list[str]) -> list[str]:
        for entry in entries:
            try:
                ipaddress.ip_network(entry.strip(), strict=False)
            except ValueError:
                raise ValueError(
                    f"{entry!r} is not an IP address or network (e.g. 10.0.0.5, 10.1.0.0/16)"
                ) from None
        return [entry.strip() for entry in entries]

    def uvicorn_proxy_options(self) -> list[str]:
        """uvicorn's options for :attr:`trusted_proxies`: believe their forwarded headers,
        or nobody's (uvicorn's own default believes 127.0.0.1: any local process could
        then claim any address)."""
        if not self.trusted_proxies:
            return ["--no-proxy-headers"]
        return ["--proxy-headers", "--forwarded-allow-ips", ",".join(self.trusted_proxies)]

    @property
    def api_dir(self) -> Path:
        """Folder of the api's own files (the generated JWT key)."""
        return self.data_dir / "api"
