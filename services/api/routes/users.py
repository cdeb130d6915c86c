"""Accounts: admins manage users; everyone reads and changes their own."""

from __future__ import annotations

from fastapi import APIRouter, Depends, status
from sqlalchemy import select

from services.api import audit
from services.api.accounts import active_admin_count, create_user, set_password
from services.api.crud import get_or_404, paginate
from services.api.deps import (
    AdminUser,
    CurrentUser,
    DbDep,
    LimiterDep,
    PageDep,
    RowId,
    get_current_user,
)
from services.api.errors import TooManyRequestsError
from services.api.ratelimit import limit_key
from services.api.schemas.common import Page
from services.api.schemas.users import PasswordChange, UserCreate, UserPublic, UserUpdate
from services.api.security import verify_password
from services.core.db.models import User
from services.core.errors import BadRequestError, ConflictError

router = APIRouter(prefix="/api/v1/users", tags=["users"], dependencies=[Depends(get_current_user)])


@router.get("/me")
def read_me(user: CurrentUser) -> UserPublic:
    """The signed-in account."""
    return UserPublic.model_validate(user)


PASSWORD_CHANGE_SCOPE = "password-change"
"""The failed-login limit counts wrong current passwords under this "address", per account."""


@router.post(
    "/me/password",
    status_code=status.HTTP_204_NO_CONTENT,
    responses={429: {"description": "Too many wrong current passwords"}},
)
def change_my_password(
    body: PasswordChange, user: CurrentUser, db: DbDep, limiter: LimiterDep
) -> None:
    """Change your own password (the current one is required; a wrong one is 422, not 401:
    the caller is signed in, the field is wrong).

    Wrong current passwords count against the failed-login limit of the account, from
    any address (``BGRL_LOGIN_MAX_FAILURES`` per ``BGRL_LOGIN_WINDOW_S``); more are a 429.
    """
    key = limit_key(PASSWORD_CHANGE_SCOPE, str(user.id))
    wait = limiter.begin(db, key)
    if wait:
        raise TooManyRequestsError(
            f"too many wrong current passwords; try again in {wait} s",
            retry_after_s=wait,
            field="current_password",
        )
    if not verify_password(user.password_hash, body.current_password):
        raise BadRequestError("current password is wrong", field="current_password")
    limiter.succeeded(db, key)
    set_password(user, body.new_password)
    audit.record(db, user, "user.password", "user", user.id)
    db.commit()


@router.post("", status_code=status.HTTP_201_CREATED)
def create(body: UserCreate, admin: AdminUser, db: DbDep) -> UserPublic:
    """Create an account (admin)."""
    user = create_user(db, body.email, body.password, body.role)
    audit.record(db, admin, "user.create", "user", user.id, email=user.email, role=user.role)
    db.commit()
    return UserPublic.model_validate(user)


@router.get("")
def list_users(_: AdminUser, db: DbDep, page: PageDep) -> Page[UserPublic]:
    """Every account (admin)."""
    return Page[UserPublic].model_validate(paginate(db, select(User).order_by(User.id), page))


@router.get("/{user_id}")
def read(user_id: RowId, _: AdminUser, db: DbDep) -> UserPublic:
    """One account (admin)."""
    return UserPublic.model_validate(get_or_404(db, User, user_id, "user_id"))


@router.patch("/{user_id}")
def update(user_id: RowId, body: UserUpdate, admin: AdminUser, db: DbDep) -> UserPublic:
    """Change an account's role, active flag or password (admin); the last admin stays."""
    user = get_or_404(db, User, user_id, "user_id")
    demoted = body.role is not None and body.role != "admin"
    deactivated = body.active is False
    last_admin = user.role == "admin" and user.active and active_admin_count(db) <= 1
    if last_admin and (demoted or deactivated):
        raise ConflictError("this is the last active admin", field="role" if demoted else "active")
    changes = body.model_dump(exclude_unset=True, exclude={"password"})
    for key, value in changes.items():
        if value is not None:
            setattr(user, key, value)
    if body.password is not None:
        set_password(user, body.password)
        changes["password"] = "changed"
    audit.record(db, admin, "user.update", "user", user.id, **changes)
    db.commit()
    return UserPublic.model_validate(user)
