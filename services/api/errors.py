"""Errors of the api besides the shared ones in :mod:`services.core.errors`."""

from __future__ import annotations

from services.core.errors import ForbiddenError, ServiceError

__all__ = ["ForbiddenError", "TooManyRequestsError", "UnauthorizedError"]


class UnauthorizedError(ServiceError):
    """No valid credentials: a missing, malformed, expired or revoked token, or a bad login."""

    status_code = 401


class TooManyRequestsError(ServiceError):
    """Too many failed logins; ``retry_after_s`` says when to try again."""

    status_code = 429

    def __init__(self, message: str, *, retry_after_s: int, field: str | None = None) -> None:
        super().__init__(message, field=field)
        self.retry_after_s = retry_after_s
