"""Passwords (argon2), access tokens (JWT, HS256) and API tokens (random, stored hashed)."""

from __future__ import annotations

import hashlib
import os
import secrets
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any, NamedTuple

import jwt
from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError

from services.api.errors import UnauthorizedError
from services.api.schemas.common import MAX_ROW_ID
from services.api.settings import ApiSettings
from services.core.db.base import utcnow

JWT_ALGORITHM = "HS256"
API_TOKEN_PREFIX = "bgrl_"
"""API tokens start with this, which tells them apart from access tokens (JWTs)."""
SHOWN_PREFIX_CHARS = 12

_hasher = PasswordHasher()


def hash_password(password: str) -> str:
    """An argon2id hash of ``password``."""
    return _hasher.hash(password)


def verify_password(password_hash: str, password: str) -> bool:
    """True if ``password`` matches ``password_hash``."""
    try:
        return _hasher.verify(password_hash, password)
    except (VerificationError, InvalidHashError):
        return False


_dummy_hashes: dict[int, str] = {}


def dummy_hash() -> str:
    """A hash of no account's password, computed once per hasher (the api computes it at
    start-up), so that a login for an unknown e-mail costs one verification, as any other."""
    dummy = _dummy_hashes.get(id(_hasher))
    if dummy is None:
        dummy = _dummy_hashes.setdefault(id(_hasher), _hasher.hash("not-a-password"))
    return dummy


def verify_nobody(password: str) -> bool:
    """Spend the time of a real verification (unknown account), so timing tells nothing."""
    verify_password(dummy_hash(), password)
    return False


def generate_password() -> str:
    """A random password for a generated account (20 URL-safe characters)."""
    return secrets.token_urlsafe(15)


def load_jwt_key(settings: ApiSettings) -> str:
    """The configured key, or the one generated at first start and kept with mode 600.

    Safe when several api processes start at once: the key is written to a private file
    that is then linked into place, so a reader sees no key file or a complete one, and
    every process ends up with the key of the first to link.
    """
    if settings.jwt_secret is not None:
        return settings.jwt_secret.get_secret_value()
    path = settings.api_dir / "jwt.key"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        draft = path.with_name(f".jwt.key.{os.getpid()}.{secrets.token_hex(4)}")
        fd = os.open(draft, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            with os.fdopen(fd, "w") as handle:
                handle.write(secrets.token_hex(32))
            os.link(draft, path)
        except FileExistsError:
            pass  # another process linked its key first: that one is used
        finally:
            draft.unlink(missing_ok=True)
    key = Path(path).read_text().strip()
    if len(key) < 32:
        raise RuntimeError(f"{path} holds a key shorter than 32 characters; delete it")
    return key


def create_access_token(user_id: int, key: str, lifetime: timedelta) -> tuple[str, datetime]:
    """A signed JWT naming the user, and when it expires."""
    now = utcnow()
    expires = now + lifetime
    # iat to the microsecond (a NumericDate may have a fraction): a token issued just
    # before a password change is told from one issued just after
    claims = {"sub": str(user_id), "iat": now.timestamp(), "exp": expires, "typ": "access"}
    return jwt.encode(claims, key, algorithm=JWT_ALGORITHM), expires


class AccessClaims(NamedTuple):
    """What a valid access token says: whose it is and when it was issued (Unix seconds)."""

    user_id: int
    issued_at: float


def decode_access_token(token: str, key: str) -> AccessClaims:
    """The claims of a valid access token; :class:`UnauthorizedError` otherwise."""
    try:
        claims: dict[str, Any] = jwt.decode(
            token, key, algorithms=[JWT_ALGORITHM], options={"require": ["exp", "iat", "sub"]}
        )
    except jwt.ExpiredSignatureError:
        raise UnauthorizedError("access token expired; log in again", field="token") from None
    except jwt.PyJWTError:
        raise UnauthorizedError("malformed or invalid access token", field="token") from None
    subject = claims.get("sub")
    if (
        claims.get("typ") != "access"
        or not isinstance(subject, str)
        or not (subject.isascii() and subject.isdigit())
        or int(subject) > MAX_ROW_ID  # no user has such an id (nor could the database hold it)
    ):
        raise UnauthorizedError("malformed or invalid access token", field="token")
    return AccessClaims(int(subject), float(claims["iat"]))


def check_issued_after_password_change(claims: AccessClaims, changed_at: datetime | None) -> None:
    """401 for an access token issued before its user's password last changed."""
    if changed_at is not None and claims.issued_at < changed_at.timestamp():
        raise UnauthorizedError(
            "access token issued before the password changed; log in again", field="token"
        )


def new_api_token() -> str:
    """A new API token (shown to its owner once; only its hash is stored)."""
    return API_TOKEN_PREFIX + secrets.token_urlsafe(32)


def hash_api_token(token: str) -> str:
    """SHA-256 of an API token (tokens are random, so a fast hash is enough)."""
    return hashlib.sha256(token.encode()).hexdigest()
