"""User accounts: creation (api, ``bgrl user``) and the first admin at first start."""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from services.api.security import generate_password, hash_password
from services.api.settings import ApiSettings
from services.core.db.base import utcnow
from services.core.db.models import ROLES, User
from services.core.errors import BadRequestError, ConflictError
from services.core.files import write_private_text

log = logging.getLogger(__name__)

EMAIL_PATTERN = r"^[^@\s]{1,64}@[^@\s]{1,255}$"
MIN_PASSWORD_CHARS = 12
DEFAULT_ADMIN_EMAIL = "admin@localhost"


def normalize_email(email: str) -> str:
    """``email`` trimmed and lower-cased; 422 if it is not an address."""
    email = email.strip().lower()
    if not re.match(EMAIL_PATTERN, email):
        raise BadRequestError(f"{email!r} is not an e-mail address", field="email")
    return email


def check_password(password: str) -> None:
    """422 unless ``password`` has at least ``MIN_PASSWORD_CHARS`` characters."""
    if len(password) < MIN_PASSWORD_CHARS:
        raise BadRequestError(
            f"password needs at least {MIN_PASSWORD_CHARS} characters", field="password"
        )


def set_password(user: User, password: str) -> None:
    """Give ``user`` a new password (not committed); the access tokens issued before it stop
    working (API tokens stay: revoke those one by one)."""
    user.password_hash = hash_password(password)
    user.password_changed_at = utcnow()


def create_user(db: Session, email: str, password: str, role: str) -> User:
    """Add a user (not committed); 409 if the e-mail is taken, 422 for a bad field."""
    email = normalize_email(email)
    check_password(password)
    if role not in ROLES:
        raise BadRequestError(f"role must be one of {', '.join(ROLES)}", field="role")
    if db.scalar(select(User.id).where(User.email == email)) is not None:
        raise ConflictError(f"a user with e-mail {email} exists", field="email")
    user = User(email=email, password_hash=hash_password(password), role=role, active=True)
    db.add(user)
    db.flush()
    return user


def active_admin_count(db: Session) -> int:
    """Number of active admins."""
    query = select(func.count()).select_from(User).where(User.role == "admin", User.active)
    return db.scalar(query) or 0


@dataclass(frozen=True)
class FirstAdmin:
    """The admin created at first start; ``password`` is set only if it was generated."""

    email: str
    generated_password: str | None


def ensure_first_admin(
    sessions: sessionmaker[Session], settings: ApiSettings, password_file: Path | None = None
) -> FirstAdmin | None:
    """Create the first admin if the database has no user at all.

    From ``BGRL_ADMIN_EMAIL``/``BGRL_ADMIN_PASSWORD`` when set; otherwise with
    ``admin@localhost`` and/or a generated password, which is returned and logged once, or
    with ``password_file``, written to that file (mode 600) and the log names the file.
    """
    with sessions() as db:
        if db.scalar(select(func.count()).select_from(User)):
            return None
        email = settings.admin_email or DEFAULT_ADMIN_EMAIL
        given = settings.admin_password.get_secret_value() if settings.admin_password else None
        password = given or generate_password()
        try:
            create_user(db, email, password, "admin")
            db.commit()
        except (ConflictError, IntegrityError):
            return None  # another process created it at the same moment
    first = FirstAdmin(email=normalize_email(email), generated_password=None if given else password)
    if first.generated_password is not None and password_file is not None:
        write_private_text(password_file, first.generated_password + "\n")
        log.warning(
            "first start: created admin %s; its password is in %s", first.email, password_file
        )
    elif first.generated_password is not None:
        log.warning(
            "first start: created admin %s with password %s (shown once; change it with "
            "POST /api/v1/users/me/password)",
            first.email,
            first.generated_password,
        )
    else:
        log.info("first start: created admin %s from BGRL_ADMIN_EMAIL", first.email)
    return first
