"""Schemas of the audit log."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from services.api.schemas.common import PublicModel


class AuditEntryPublic(PublicModel):
    """Who did what to which resource, and when."""

    id: int
    at: datetime
    actor_id: int | None
    actor_email: str | None
    action: str
    target_type: str
    target_id: str | None
    detail: dict[str, Any]
