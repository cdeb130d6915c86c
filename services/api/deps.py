"""FastAPI dependencies of the api (``Annotated`` aliases used by the routes)."""

from __future__ import annotations

from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Annotated

from celery import Celery
from fastapi import Depends, Path, Query, WebSocket
from fastapi.security import OAuth2PasswordBearer
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker
from starlette.requests import HTTPConnection

from services.api.errors import ForbiddenError, UnauthorizedError
from services.api.ratelimit import LoginLimiter
from services.api.schemas.common import MAX_ROW_ID
from services.api.security import API_TOKEN_PREFIX, decode_access_token, hash_api_token
from services.api.settings import ApiSettings
from services.core.artifacts import ArtifactStore
from services.core.db.base import utcnow
from services.core.db.models import ApiToken, User
from services.core.websockets import CLOSE_UNAUTHORIZED

TOKEN_URL = "/api/v1/auth/token"
ROLE_RANK = {"viewer": 0, "staff": 1, "admin": 2}
MAX_PAGE_LIMIT = 500

bearer_scheme = OAuth2PasswordBearer(tokenUrl=TOKEN_URL, auto_error=False)


async def get_settings(connection: HTTPConnection) -> ApiSettings:
    """The settings the app was built with."""
    return connection.app.state.settings


async def get_db(connection: HTTPConnection) -> AsyncIterator[Session]:
    """A database session for this request (closed afterwards; routes commit).

    A request's session keeps its connection across the request's thread hops (sign-in,
    then the route), so with more requests in flight than the pool has connections, every
    thread could wait for a connection held by a request that waits for a thread: a
    deadlock until the pool's timeout. ``app.state.db_slots`` (one slot per pooled
    connection) admits only as many requests as can hold a connection; the others wait on
    the event loop. Closing returns the connection (a rollback at most), done on the loop
    so that releasing never needs a free thread.
    """
    factory: sessionmaker[Session] = connection.app.state.sessions
    async with connection.app.state.db_slots:
        session = factory()
        try:
            yield session
        finally:
            session.close()


async def get_store(connection: HTTPConnection) -> ArtifactStore:
    """The artifact store."""
    return connection.app.state.store


async def get_celery(connection: HTTPConnection) -> Celery:
    """The Celery client jobs are enqueued with."""
    return connection.app.state.celery


async def get_limiter(connection: HTTPConnection) -> LoginLimiter:
    """The failed-login limiter."""
    return connection.app.state.limiter


def authenticate(db: Session, token: str, jwt_key: str) -> User:
    """The active user an access token or API token belongs to; 401 otherwise."""
    if token.startswith(API_TOKEN_PREFIX):
        row = db.scalar(select(ApiToken).where(ApiToken.token_hash == hash_api_token(token)))
        now = utcnow()
        if row is None or row.revoked_at is not None:
            raise UnauthorizedError("unknown or revoked API token", field="token")
        if row.expires_at is not None and row.expires_at <= now:
            raise UnauthorizedError("API token expired", field="token")
        user_id = row.user_id
        if row.last_used_at is None or (now - row.last_used_at).total_seconds() > 60:
            row.last_used_at = now
            db.commit()
    else:
        user_id = decode_access_token(token, jwt_key)
    user = db.get(User, user_id)
    if user is None or not user.active:
        raise UnauthorizedError("account unknown or deactivated", field="token")
    return user


def websocket_token(websocket: WebSocket, token: str | None) -> str | None:
    """The user's token of a websocket: ``?token=`` (browsers cannot set headers on
    websockets) or an ``Authorization: Bearer`` header."""
    header = websocket.headers.get("authorization", "")
    if token is None and header.lower().startswith("bearer "):
        return header[7:].strip()
    return token


def websocket_sign_in_refusal(
    db: Session, websocket: WebSocket, token: str | None
) -> tuple[int, str] | None:
    """``(close code, reason)`` if the websocket's user is not signed in, else None."""
    if not token:
        return CLOSE_UNAUTHORIZED, "not signed in: pass ?token= or an Authorization header"
    try:
        authenticate(db, token, websocket.app.state.jwt_key)
    except UnauthorizedError as exc:
        return CLOSE_UNAUTHORIZED, str(exc)
    return None


def get_current_user(
    connection: HTTPConnection,
    db: Annotated[Session, Depends(get_db)],
    token: Annotated[str | None, Depends(bearer_scheme)],
) -> User:
    """The signed-in user (any role): a bearer access token or API token is required."""
    if not token:
        raise UnauthorizedError(
            "not signed in: send 'Authorization: Bearer <token>'", field="token"
        )
    return authenticate(db, token, connection.app.state.jwt_key)


def _require(role: str, user: User) -> User:
    if ROLE_RANK[user.role] < ROLE_RANK[role]:
        raise ForbiddenError(f"this needs the {role} role (you are {user.role})", field="role")
    return user


def require_staff(user: Annotated[User, Depends(get_current_user)]) -> User:
    """The signed-in user if staff or admin; 403 otherwise."""
    return _require("staff", user)


def require_admin(user: Annotated[User, Depends(get_current_user)]) -> User:
    """The signed-in user if admin; 403 otherwise."""
    return _require("admin", user)


@dataclass(frozen=True)
class PageParams:
    """``limit`` and ``offset`` of a list route."""

    limit: int
    offset: int


async def get_page(
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE_LIMIT, description="Items per page.")] = 50,
    offset: Annotated[int, Query(ge=0, le=10**9, description="Items to skip.")] = 0,
) -> PageParams:
    """Pagination parameters (at most ``MAX_PAGE_LIMIT`` items per page)."""
    return PageParams(limit=limit, offset=offset)


SettingsDep = Annotated[ApiSettings, Depends(get_settings)]
DbDep = Annotated[Session, Depends(get_db)]
StoreDep = Annotated[ArtifactStore, Depends(get_store)]
CeleryDep = Annotated[Celery, Depends(get_celery)]
LimiterDep = Annotated[LoginLimiter, Depends(get_limiter)]
CurrentUser = Annotated[User, Depends(get_current_user)]
StaffUser = Annotated[User, Depends(require_staff)]
AdminUser = Annotated[User, Depends(require_admin)]
PageDep = Annotated[PageParams, Depends(get_page)]
RowId = Annotated[int, Path(ge=1, le=MAX_ROW_ID)]
"""An integer id in a path."""
