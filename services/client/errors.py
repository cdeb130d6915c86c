"""Errors of the platform client: every failure is a :class:`PlatformError`."""

from __future__ import annotations

from typing import Any

import httpx


class PlatformError(Exception):
    """A request failed: ``status`` is the HTTP status (None if the api was not reached),
    ``detail`` the api's one-line explanation and ``field`` the input it names, if any."""

    def __init__(self, detail: str, *, status: int | None = None, field: str | None = None):
        super().__init__(detail)
        self.detail = detail
        self.status = status
        self.field = field

    def __str__(self) -> str:
        where = f" (field {self.field})" if self.field else ""
        code = f"HTTP {self.status}: " if self.status is not None else ""
        return f"{code}{self.detail}{where}"

    @property
    def is_bad_input(self) -> bool:
        """True when the api refused the request's content (400 or 422)."""
        return self.status in (400, 422)


class ChecksumMismatchError(PlatformError):
    """A download's bytes do not hash to the ``X-Checksum-Sha256`` the api sent; the file
    was not kept."""


class WaitTimeoutError(PlatformError, TimeoutError):
    """A job did not finish within the time given to :meth:`PlatformClient.wait_job`."""


def error_from_response(response: httpx.Response) -> PlatformError:
    """The :class:`PlatformError` of a 4xx/5xx answer, from the api's JSON body.

    The api answers ``{"detail": "...", "field": "..."}``, or for a validation error (422)
    ``{"detail": [{"field", "msg", ...}], "message": "..."}``.
    """
    try:
        body: Any = response.json()
    except ValueError:
        body = None
    detail: str = response.reason_phrase or "request failed"
    field: str | None = None
    if isinstance(body, dict):
        raw = body.get("detail")
        if isinstance(raw, str):
            detail = raw
            field = body.get("field") if isinstance(body.get("field"), str) else None
        elif isinstance(raw, list) and raw:
            entries = [e for e in raw if isinstance(e, dict)]
            if entries:
                first = entries[0].get("field")
                field = first if isinstance(first, str) else None
            message = body.get("message")
            if isinstance(message, str) and message:
                detail = message
            else:
                detail = "; ".join(str(e.get("msg", e)) for e in entries) or detail
    elif response.text and len(response.text) < 300:
        detail = response.text.strip()
    return PlatformError(detail, status=response.status_code, field=field)
