"""API tokens for scripts: created by their owner, shown once, revocable."""

from __future__ import annotations

from datetime import timedelta

from fastapi import APIRouter, Depends, status
from sqlalchemy import select

from services.api import audit
from services.api.crud import get_or_404, paginate
from services.api.deps import BearerToken, CurrentUser, DbDep, PageDep, RowId, get_current_user
from services.api.errors import ForbiddenError
from services.api.schemas.auth import ApiTokenCreate, ApiTokenCreated, ApiTokenPublic
from services.api.schemas.common import Page
from services.api.security import (
    API_TOKEN_PREFIX,
    SHOWN_PREFIX_CHARS,
    hash_api_token,
    new_api_token,
)
from services.core.db.base import utcnow
from services.core.db.models import ApiToken
from services.core.errors import NotFoundError

router = APIRouter(
    prefix="/api/v1/tokens", tags=["tokens"], dependencies=[Depends(get_current_user)]
)


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    responses={403: {"description": "Signed in with an API token (sign in with a password)"}},
)
def create(
    body: ApiTokenCreate, user: CurrentUser, token: BearerToken, db: DbDep
) -> ApiTokenCreated:
    """A new API token acting as you (with your role); the token is in this answer only.

    Only a password sign-in (an access token) creates API tokens: an API token cannot mint
    others, so revoking a leaked one ends what it could do.
    """
    if token.startswith(API_TOKEN_PREFIX):
        raise ForbiddenError(
            "an API token cannot create API tokens; sign in with your password", field="token"
        )
    token = new_api_token()
    expires = (
        None if body.expires_in_days is None else utcnow() + timedelta(days=body.expires_in_days)
    )
    row = ApiToken(
        user_id=user.id,
        name=body.name,
        token_prefix=token[:SHOWN_PREFIX_CHARS],
        token_hash=hash_api_token(token),
        expires_at=expires,
    )
    db.add(row)
    db.flush()
    audit.record(db, user, "token.create", "api_token", row.id, name=body.name)
    db.commit()
    return ApiTokenCreated(**ApiTokenPublic.model_validate(row).model_dump(), token=token)


@router.get("")
def list_tokens(user: CurrentUser, db: DbDep, page: PageDep) -> Page[ApiTokenPublic]:
    """Your API tokens (admins see everyone's)."""
    query = select(ApiToken).order_by(ApiToken.id)
    if user.role != "admin":
        query = query.where(ApiToken.user_id == user.id)
    return Page[ApiTokenPublic].model_validate(paginate(db, query, page))


@router.delete("/{token_id}", status_code=status.HTTP_204_NO_CONTENT)
def revoke(token_id: RowId, user: CurrentUser, db: DbDep) -> None:
    """Revoke one of your API tokens (admins: anyone's); it stops working at once."""
    row = get_or_404(db, ApiToken, token_id, "token_id")
    if row.user_id != user.id and user.role != "admin":
        raise NotFoundError(f"no api token with id {token_id}", field="token_id")
    if row.revoked_at is None:
        row.revoked_at = utcnow()
        audit.record(db, user, "token.revoke", "api_token", row.id)
        db.commit()
