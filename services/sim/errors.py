"""Errors of the sim service; each carries the HTTP status the app answers with.

They subclass :class:`services.core.errors.ServiceError`, so the platform's one handler
turns them into ``{"detail": message, "field": name-or-null}`` with their status.
"""

from __future__ import annotations

from services.core.errors import ServiceError


class SimServiceError(ServiceError):
    """A request the sim service refuses; ``str(exc)`` is the message sent to the client."""

    status_code = 400


class SessionNotFoundError(SimServiceError):
    """No session has this id."""

    status_code = 404


class SessionClosedError(SimServiceError):
    """The session existed but was closed."""

    status_code = 410


class SessionLimitError(SimServiceError):
    """Opening one more session would exceed ``max_sessions``."""

    status_code = 409


class EpisodeOverError(SimServiceError):
    """A step was requested after the episode terminated or was truncated."""

    status_code = 409


class PacedModeError(SimServiceError):
    """The request conflicts with the session's paced mode (running or not running)."""

    status_code = 409


class MapRequestError(SimServiceError):
    """The requested map is unknown, not allowed, or invalid (field ``map``)."""

    status_code = 422

    def __init__(self, message: str, *, field: str | None = "map") -> None:
        super().__init__(message, field=field)


class BadQueryError(SimServiceError):
    """A query parameter is out of range (the field names it)."""

    status_code = 422
