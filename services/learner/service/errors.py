"""Errors of the learner service; each carries the HTTP status the app answers with.

They subclass :class:`services.core.errors.ServiceError`, so the platform's one handler
turns them into ``{"detail": message, "field": name-or-null}`` with their status.
"""

from __future__ import annotations

from services.core.errors import ServiceError


class LearnerServiceError(ServiceError):
    """A request the learner service refuses; ``str(exc)`` is the message sent to the client."""

    status_code = 400


class HFSessionNotFoundError(LearnerServiceError):
    """No HF session has this id."""

    status_code = 404


class SessionLimitError(LearnerServiceError):
    """Creating one more session would exceed ``max_sessions``."""

    status_code = 409


class LabelBudgetError(LearnerServiceError):
    """The session already has all the labels of its budget."""

    status_code = 409


class MarkerConflictError(LearnerServiceError):
    """A marker id already labelled is sent again with a different label."""

    status_code = 409


class InvalidRequestError(LearnerServiceError):
    """A field is well-formed but unusable (unknown map, budget too large...); names it."""

    status_code = 422
