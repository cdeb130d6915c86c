"""Base classes of request schemas (unknown fields and non-finite numbers are refused) and
the field types the services validate alike: an action and a seed."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

from services.core.actions import Action

ActionValue = Annotated[
    int,
    Field(
        strict=True,  # JSON integers only: no "1", true or 1.0
        ge=min(Action),
        le=max(Action),
        description="0 forward 0.3 m, 1 turn left 30 deg, 2 turn right 30 deg.",
    ),
]
"""An action of the navigation task, as a JSON integer."""
Seed = Annotated[
    int, Field(strict=True, ge=0, le=2**63 - 1, description="A JSON integer in [0, 2^63).")
]
"""A seed, as a JSON integer in [0, 2^63)."""
MAX_ROW_ID = 2**31 - 1
"""Largest integer id accepted (bigger ones cannot exist and would overflow the database)."""


class StrictRequest(BaseModel):
    """A request body: a typo'd field is a 422, and so is ``NaN``, ``Infinity`` or ``1e400``."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class FiniteModel(BaseModel):
    """A model whose floats must be finite (JSON cannot carry NaN or infinities)."""

    model_config = ConfigDict(allow_inf_nan=False)
