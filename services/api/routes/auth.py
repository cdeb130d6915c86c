"""Sign-in: the OAuth2 password flow issuing short-lived access tokens (JWT)."""

from __future__ import annotations

import logging
from datetime import timedelta
from typing import Annotated

from fastapi import APIRouter, Depends, Request
from fastapi.security import OAuth2PasswordRequestForm
from sqlalchemy import select

from services.api.deps import DbDep, LimiterDep, SettingsDep
from services.api.errors import TooManyRequestsError, UnauthorizedError
from services.api.ratelimit import limit_key
from services.api.schemas.auth import AccessToken
from services.api.security import create_access_token, verify_nobody, verify_password
from services.core.db.base import utcnow
from services.core.db.models import User

log = logging.getLogger(__name__)
router = APIRouter(prefix="/api/v1/auth", tags=["auth"])


@router.post(
    "/token",
    responses={
        401: {"description": "Wrong e-mail or password"},
        429: {"description": "Too many failed logins"},
    },
)
def login(
    request: Request,
    form: Annotated[OAuth2PasswordRequestForm, Depends()],
    db: DbDep,
    settings: SettingsDep,
    limiter: LimiterDep,
) -> AccessToken:
    """Exchange e-mail (``username``) and password for a bearer access token."""
    email = form.username.strip().lower()
    client = request.client.host if request.client else "?"
    key = limit_key(client, email)
    wait = limiter.begin(db, key)
    if wait:
        raise TooManyRequestsError(
            f"too many failed logins; try again in {wait} s", retry_after_s=wait, field="username"
        )
    # an address with a NUL character names nobody (and PostgreSQL cannot compare it)
    user = None if "\x00" in email else db.scalar(select(User).where(User.email == email))
    if user is None:
        valid = verify_nobody(form.password)
    else:
        valid = verify_password(user.password_hash, form.password)
    if user is None or not valid or not user.active:
        log.info("failed login for %s from %s", email, client)
        raise UnauthorizedError(
            "wrong e-mail or password, or account deactivated", field="password"
        )
    limiter.succeeded(db, key)
    user.last_login_at = utcnow()
    db.commit()
    token, expires = create_access_token(
        user.id, request.app.state.jwt_key, timedelta(minutes=settings.access_token_minutes)
    )
    return AccessToken(access_token=token, expires_at=expires)
