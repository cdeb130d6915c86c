"""Failed-login limit: too many failures for one account from one address are refused.

The count lives in the database (``login_attempts``), so every api process using it (the
``BGRL_API_WORKERS`` processes of ``bgrl up``, replicas on other hosts) shares one limit.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable
from datetime import datetime, timedelta

from sqlalchemy import delete, select, text
from sqlalchemy.orm import Session

from services.core.db.base import utcnow
from services.core.db.models import LoginAttempt

PG_LOCK_SPACE = 0x62676C6C
"""First key of the PostgreSQL advisory locks that serialise one login key's attempts."""


def limit_key(address: str, account: str) -> str:
    """The key failures are counted under: SHA-256 of client address and account."""
    return hashlib.sha256(f"{address}|{account}".encode()).hexdigest()


class LoginLimiter:
    """At most ``max_failures`` failed logins per key in any sliding window of ``window_s``.

    :meth:`begin` records an attempt before the password is checked and :meth:`succeeded`
    deletes the key's attempts, so a key's rows within the window are its failures. Counting
    and recording happen under a lock (PostgreSQL: an advisory lock per key; SQLite: the
    database's write lock), so attempts racing on one key, from any process, are admitted
    exactly up to the limit. Rows older than the window are pruned on every admitted attempt,
    so the table holds at most one window's attempts.
    """

    def __init__(
        self, max_failures: int, window_s: float, clock: Callable[[], datetime] = utcnow
    ) -> None:
        self.max_failures = max_failures
        self.window = timedelta(seconds=window_s)
        self.clock = clock

    def begin(self, db: Session, key: str) -> int:
        """Start an attempt of ``key``: 0 if it may go on (it counts as a failure until
        :meth:`succeeded`), else the seconds to wait (nothing is recorded). Commits."""
        now = self.clock()
        wait = self._wait(db, key, now)  # without a lock: a refused key writes nothing
        db.rollback()
        if wait:
            return wait
        self._lock(db, key)
        # Prune: rows another attempt is deleting are skipped (PostgreSQL), so concurrent
        # attempts never wait on each other's rows. On SQLite this first write of the
        # transaction takes the database's write lock.
        stale = (
            select(LoginAttempt.id)
            .where(LoginAttempt.at <= now - self.window)
            .with_for_update(skip_locked=True)
        )
        db.execute(delete(LoginAttempt).where(LoginAttempt.id.in_(stale)))
        wait = self._wait(db, key, now)
        if not wait:
            db.add(LoginAttempt(key=key, at=now))
        db.commit()
        return wait

    def succeeded(self, db: Session, key: str) -> None:
        """Forget the attempts of ``key`` after a successful login (the caller commits)."""
        self._lock(db, key)
        db.execute(delete(LoginAttempt).where(LoginAttempt.key == key))

    @staticmethod
    def _lock(db: Session, key: str) -> None:
        """PostgreSQL: wait for the key's advisory lock (held until the transaction ends)."""
        if db.get_bind().dialect.name == "postgresql":
            db.execute(
                text("SELECT pg_advisory_xact_lock(:space, :key)"),
                {
                    "space": PG_LOCK_SPACE,
                    "key": int.from_bytes(bytes.fromhex(key[:8]), "big", signed=True),
                },
            )

    def _wait(self, db: Session, key: str, now: datetime) -> int:
        """Seconds until ``key`` has fewer than ``max_failures`` attempts in the window."""
        recent = db.scalars(
            select(LoginAttempt.at)
            .where(LoginAttempt.key == key, LoginAttempt.at > now - self.window)
            .order_by(LoginAttempt.at.desc())
            .limit(self.max_failures)
        ).all()
        if len(recent) < self.max_failures:
            return 0
        frees_at = recent[-1] + self.window
        return max(1, math.ceil((frees_at - now).total_seconds()))
