"""The error every service raises for a request it refuses; each carries its HTTP status.

Service code raises a subclass of :class:`ServiceError` (never ``HTTPException``); the one
handler installed by :func:`services.core.web.create_service_app` turns it into a JSON body
``{"detail": message, "field": name-or-null}`` with the class's status code.
"""

from __future__ import annotations


class ServiceError(Exception):
    """A request a service refuses; ``str(exc)`` is the message sent to the client."""

    status_code = 400

    def __init__(self, message: str, *, field: str | None = None) -> None:
        super().__init__(message)
        self.field = field


class BadRequestError(ServiceError):
    """The request is well-formed JSON but asks for something impossible."""

    status_code = 422


class NotFoundError(ServiceError):
    """No resource has this id."""

    status_code = 404


class ConflictError(ServiceError):
    """The request conflicts with the resource's current state."""

    status_code = 409


class GoneError(ServiceError):
    """The resource existed but is closed."""

    status_code = 410


class PayloadTooLargeError(ServiceError):
    """The request body is larger than the endpoint accepts."""

    status_code = 413


class UnsupportedMediaError(ServiceError):
    """The body's format is not one the endpoint accepts."""

    status_code = 415


class InsufficientStorageError(ServiceError):
    """The data disk is (nearly) full: nothing was stored (see :mod:`services.core.disk`)."""

    status_code = 507


class ForbiddenError(ServiceError):
    """Valid credentials (or none needed to say so) that do not allow this request."""

    status_code = 403
