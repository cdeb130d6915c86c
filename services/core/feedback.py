"""The decision rule that turns a classifier's P(error) into binary feedback, and the label
channels stage 2 can read a decoded epoch through."""

from __future__ import annotations

from typing import Literal

P_ERROR_THRESHOLD = 0.5
"""An epoch with P(error) at or above this is decoded as an error (ErrP present)."""


def is_error(p_error: float) -> bool:
    """True when ``p_error`` decodes to "error" (the robot's action was judged wrong)."""
    return p_error >= P_ERROR_THRESHOLD


LabelChannel = Literal["hard", "soft"]
"""How stage 2 reads a decoded epoch: ``hard``, the thresholded label under a label-noise
model (the paper); ``soft``, the calibrated likelihood ratio P(epoch | error) /
P(epoch | correct) (docs/stage2.md, "Soft labels")."""
LABEL_CHANNELS: tuple[str, ...] = LabelChannel.__args__  # type: ignore[attr-defined]
