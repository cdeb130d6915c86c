"""The decision rule that turns a classifier's P(error) into binary feedback."""

from __future__ import annotations

P_ERROR_THRESHOLD = 0.5
"""An epoch with P(error) at or above this is decoded as an error (ErrP present)."""


def is_error(p_error: float) -> bool:
    """True when ``p_error`` decodes to "error" (the robot's action was judged wrong)."""
    return p_error >= P_ERROR_THRESHOLD
