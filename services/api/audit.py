"""The audit log: who did what to which resource (written in the same transaction)."""

from __future__ import annotations

from typing import Any

from sqlalchemy.orm import Session

from services.core.db.models import AuditEntry, User


def record(
    db: Session,
    actor: User | None,
    action: str,
    target_type: str,
    target_id: object = None,
    **detail: Any,
) -> None:
    """Add an audit entry to ``db``'s transaction (committed with the change it describes)."""
    db.add(
        AuditEntry(
            actor_id=actor.id if actor is not None else None,
            actor_email=actor.email if actor is not None else None,
            action=action,
            target_type=target_type,
            target_id=None if target_id is None else str(target_id),
            detail=detail,
        )
    )
