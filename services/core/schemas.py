"""Base classes of request schemas: unknown fields and non-finite numbers are refused."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class StrictRequest(BaseModel):
    """A request body: a typo'd field is a 422, and so is ``NaN``, ``Infinity`` or ``1e400``."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class FiniteModel(BaseModel):
    """A model whose floats must be finite (JSON cannot carry NaN or infinities)."""

    model_config = ConfigDict(allow_inf_nan=False)
