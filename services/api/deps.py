"""FastAPI dependencies of the api (``Annotated`` aliases used by the routes)."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from dataclasses import dataclass
from datetime import timedelta
from typing import Annotated, TypeVar

from celery import Celery
from fastapi import Depends, Path, Query, WebSocket
from fastapi.concurrency import run_in_threadpool
from fastapi.security import OAuth2PasswordBearer
from sqlalchemy import bindparam, or_, select, update
from sqlalchemy.orm import Session, sessionmaker
from starlette.requests import HTTPConnection

from services.api.errors import ForbiddenError, UnauthorizedError
from services.api.ratelimit import LoginLimiter
from services.api.schemas.common import MAX_ROW_ID
from services.api.security import (
    API_TOKEN_PREFIX,
    check_issued_after_password_change,
    decode_access_token,
    hash_api_token,
)
from services.api.settings import ApiSettings
from services.core.artifacts import ArtifactStore
from services.core.db.base import utcnow
from services.core.db.models import ApiToken, User
from services.core.websockets import CLOSE_UNAUTHORIZED

T = TypeVar("T")
TOKEN_URL = "/api/v1/auth/token"
ROLE_RANK = {"viewer": 0, "staff": 1, "admin": 2}
DEFAULT_PAGE_LIMIT = 50
MAX_PAGE_LIMIT = 500
MAX_PAGE_OFFSET = 10**9

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


NOT_SIGNED_IN = "not signed in: send 'Authorization: Bearer <token>'"
API_TOKEN_USE_RESOLUTION_S = 60
"""An API token's ``last_used_at`` is written when older than this (not on every request)."""


API_TOKEN_SIGN_IN = (
    select(
        User,
        ApiToken.id.label("token_id"),
        ApiToken.revoked_at,
        ApiToken.expires_at,
        ApiToken.last_used_at,
    )
    .join(User, User.id == ApiToken.user_id)
    .where(ApiToken.token_hash == bindparam("token_hash"))
)
"""An API token (by its SHA-256: a unique index) and its user, in one query."""
API_TOKEN_USED = (
    update(ApiToken)
    .where(ApiToken.id == bindparam("token_id"))
    .where(or_(ApiToken.last_used_at.is_(None), ApiToken.last_used_at < bindparam("stale_before")))
    .values(last_used_at=bindparam("now"))
)
"""Record a token's use unless another request did within the resolution: the requests that
all read the old time at once then write it once. Unconditional, each would wait for the
row's lock and its predecessor's commit (on PostgreSQL an fsync, ~4 ms here) in turn: a
chain of commits every minute that the requests behind them queue for."""


def _api_token_user(db: Session, token: str) -> User:
    """The user of a valid API token (active or not): one indexed query, checked now, so
    a revocation takes effect at once; its use is recorded (committed) at most once a
    minute. 401 for an unknown, revoked or expired token."""
    row = db.execute(API_TOKEN_SIGN_IN, {"token_hash": hash_api_token(token)}).first()
    now = utcnow()
    if row is None or row.revoked_at is not None:
        raise UnauthorizedError("unknown or revoked API token", field="token")
    if row.expires_at is not None and row.expires_at <= now:
        raise UnauthorizedError("API token expired", field="token")
    last_used = row.last_used_at
    stale_before = now - timedelta(seconds=API_TOKEN_USE_RESOLUTION_S)
    if last_used is None or last_used < stale_before:
        db.execute(
            API_TOKEN_USED, {"token_id": row.token_id, "stale_before": stale_before, "now": now}
        )
        db.commit()
    return row.User


def authenticate(db: Session, token: str, jwt_key: str) -> User:
    """The active user an access token or API token belongs to; 401 otherwise."""
    claims = None
    user: User | None
    if token.startswith(API_TOKEN_PREFIX):
        user = _api_token_user(db, token)
    else:
        claims = decode_access_token(token, jwt_key)
        user = db.get(User, claims.user_id)
    if user is None or not user.active:
        raise UnauthorizedError("account unknown or deactivated", field="token")
    if claims is not None:
        check_issued_after_password_change(claims, user.password_changed_at)
    return user


async def bearer_token(token: Annotated[str | None, Depends(bearer_scheme)]) -> str:
    """The bearer token sent, not yet checked (:func:`get_current_user` checks it); 401 if
    none."""
    if not token:
        raise UnauthorizedError(NOT_SIGNED_IN, field="token")
    return token


WEBSOCKET_PROTOCOL = "bgrl"
"""The subprotocol a browser offers beside ``bearer.<token>``; the api answers with it
(a server must name one the client offered, and never the token)."""
BEARER_PROTOCOL_PREFIX = "bearer."
"""A websocket subprotocol ``bearer.<token>`` carries the user's token."""
REVOCATION_CHECK_S = 0.5
"""An open websocket re-checks its token this often: closed within a second of a revocation."""
WEBSOCKET_SIGN_IN = (
    "not signed in: offer the subprotocols 'bgrl' and 'bearer.<token>' "
    "(Sec-WebSocket-Protocol) or send an Authorization header"
)


def websocket_token(websocket: WebSocket) -> str | None:
    """The user's token of a websocket: an ``Authorization: Bearer`` header or, from a
    browser (which cannot set headers on websockets), the subprotocol ``bearer.<token>``.
    Never the URL: URLs end up in access logs and browser histories."""
    header = websocket.headers.get("authorization", "")
    if header.lower().startswith("bearer "):
        return header[7:].strip()
    for protocol in websocket.scope.get("subprotocols", []):
        if protocol.startswith(BEARER_PROTOCOL_PREFIX):
            return protocol[len(BEARER_PROTOCOL_PREFIX) :]
    return None


def websocket_subprotocol(websocket: WebSocket) -> str | None:
    """The subprotocol to accept with: ``bgrl`` if the client offered it, else none."""
    offered = websocket.scope.get("subprotocols", [])
    return WEBSOCKET_PROTOCOL if WEBSOCKET_PROTOCOL in offered else None


def websocket_sign_in_refusal(db: Session, websocket: WebSocket) -> tuple[int, str] | None:
    """``(close code, reason)`` if the websocket's user is not signed in, else None (a token
    in the URL is refused, however valid: it has been logged on its way)."""
    if "token" in websocket.query_params:
        return CLOSE_UNAUTHORIZED, "a token in the URL is refused (URLs are logged); " + (
            WEBSOCKET_SIGN_IN.removeprefix("not signed in: ")
        )
    token = websocket_token(websocket)
    if not token:
        return CLOSE_UNAUTHORIZED, WEBSOCKET_SIGN_IN
    try:
        authenticate(db, token, websocket.app.state.jwt_key)
    except UnauthorizedError as exc:
        return CLOSE_UNAUTHORIZED, str(exc)
    return None


def _signed_out(websocket: WebSocket) -> tuple[int, str] | None:
    with websocket.app.state.sessions() as db:
        return websocket_sign_in_refusal(db, websocket)


async def until_signed_out(websocket: WebSocket) -> tuple[int, str]:
    """Wait until the accepted websocket's token stops working (revoked or expired, its
    account deactivated, its password changed); ``(close code, reason)`` then."""
    while True:
        await asyncio.sleep(REVOCATION_CHECK_S)
        refused = await run_in_threadpool(_signed_out, websocket)
        if refused is not None:
            return refused


def get_current_user(
    connection: HTTPConnection,
    db: Annotated[Session, Depends(get_db)],
    token: Annotated[str | None, Depends(bearer_scheme)],
) -> User:
    """The signed-in user (any role): a bearer access token or API token is required."""
    if not token:
        raise UnauthorizedError(NOT_SIGNED_IN, field="token")
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
    limit: Annotated[
        int, Query(ge=1, le=MAX_PAGE_LIMIT, description="Items per page.")
    ] = DEFAULT_PAGE_LIMIT,
    offset: Annotated[int, Query(ge=0, le=MAX_PAGE_OFFSET, description="Items to skip.")] = 0,
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
BearerToken = Annotated[str, Depends(bearer_token)]
RowId = Annotated[int, Path(ge=1, le=MAX_ROW_ID)]
"""An integer id in a path."""
