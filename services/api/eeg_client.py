"""Validation of recordings by the EEG service, over HTTP (the api does not import it)."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx

from services.core.web import SERVICE_TOKEN_HEADER

log = logging.getLogger(__name__)

CHUNK_BYTES = 1024 * 1024


@dataclass(frozen=True)
class Validation:
    """What the EEG pipeline found: ``valid``, ``invalid`` (with the reason) or ``pending``.

    ``pending`` means it could not be asked (service down or not configured); the reason
    says why, and validation can be retried.
    """

    status: str
    reason: str | None = None
    synthetic: bool | None = None
    n_channels: int | None = None
    sfreq: float | None = None
    duration_s: float | None = None


def _file_chunks(path: Path) -> Iterator[bytes]:
    with path.open("rb") as handle:
        while chunk := handle.read(CHUNK_BYTES):
            yield chunk


def validate_recording(
    path: Path,
    filename: str,
    *,
    eeg_url: str | None,
    timeout_s: float,
    service_token: str | None = None,
) -> Validation:
    """Send the file to the EEG service's ``POST /recordings`` and read its verdict."""
    if not eeg_url:
        return Validation("pending", "no EEG service configured (BGRL_EEG_URL)")
    headers = {"content-type": "application/octet-stream"}
    if service_token:
        headers[SERVICE_TOKEN_HEADER] = service_token
    try:
        with httpx.Client(base_url=eeg_url, timeout=timeout_s) as client:
            response = client.post(
                "/recordings",
                params={"filename": filename},
                content=_file_chunks(path),
                headers=headers,
            )
    except httpx.HTTPError as exc:
        log.warning("EEG service at %s unreachable: %s", eeg_url, exc)
        return Validation("pending", f"EEG service at {eeg_url} unreachable ({type(exc).__name__})")
    if response.status_code in (200, 201):
        meta = response.json()
        return Validation(
            "valid",
            None,
            synthetic=bool(meta.get("synthetic")),
            n_channels=meta.get("n_channels"),
            sfreq=meta.get("sfreq"),
            duration_s=meta.get("duration_s"),
        )
    try:
        detail = response.json().get("detail")
    except ValueError:
        detail = None
    if response.status_code in (413, 415, 422) and detail:
        return Validation("invalid", str(detail)[:2000])
    log.warning("EEG service answered %s to a validation", response.status_code)
    return Validation("pending", f"EEG service answered HTTP {response.status_code}; retry later")
