"""Errors of the EEG service; each carries the HTTP status the app answers with.

Service code raises these (never ``HTTPException``); the handler installed by
:func:`services.core.web.create_service_app` turns them into ``{"detail", "field"}``.
"""

from __future__ import annotations

from services.core.errors import (
    BadRequestError,
    ConflictError,
    NotFoundError,
    ServiceError,
    UnsupportedMediaError,
)


class RecordingNotFoundError(NotFoundError):
    """No stored recording has this id."""


class JobNotFoundError(NotFoundError):
    """No calibration job has this id."""


class ClassifierNotFoundError(NotFoundError):
    """No trained classifier has this id."""


class ClassifierUnusableError(ConflictError):
    """The classifier's files exist but cannot be loaded."""


class InvalidRecordingError(BadRequestError):
    """The uploaded file is a recording format we read, but not a usable recording."""


class UnsupportedFormatError(UnsupportedMediaError):
    """The uploaded file is not BDF, EDF or FIF."""


class UploadAbortedError(ServiceError):
    """The client stopped sending the body before it was complete."""

    status_code = 400


class JobStateError(ConflictError):
    """The job's status does not allow the request (e.g. cancelling a finished job)."""


class EpochMismatchError(BadRequestError):
    """An epoch to classify does not match the classifier (shape, channels, rate, units)."""


class NoLiveSourceError(ConflictError):
    """A marker was sent while no live EEG source is connected."""


class LiveSourceError(BadRequestError):
    """The LSL stream to connect is missing or does not match the classifier."""
