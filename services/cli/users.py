"""``bgrl user``: accounts of the platform, straight in its database (e.g. the first admin)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

user_app = typer.Typer(
    help="Platform accounts, straight in the platform database (BGRL_DATABASE_URL, or "
    "BGRL_DATA_DIR/bgrl.db); each command names the database it uses.",
    no_args_is_help=True,
)


def _sessions(create_database: bool = False) -> Any:
    """The session factory of the platform database, named on stderr; a one-line error if
    there is none (no SQLite file, or a database without the platform's tables) unless
    ``create_database``: a command run from the wrong folder must not make an empty one."""
    from sqlalchemy.engine import make_url

    from services.api.settings import ApiSettings
    from services.core.db.migrate import current_revision, upgrade_database
    from services.core.db.session import make_engine, make_session_factory
    from services.core.settings import SettingsError, load_settings

    try:
        settings = load_settings(ApiSettings)
    except SettingsError as exc:
        raise typer.BadParameter(str(exc)) from None
    url = settings.resolved_database_url
    parsed = make_url(url)
    shown = parsed.render_as_string(hide_password=True)
    typer.echo(f"database: {shown}", err=True)
    sqlite_file = parsed.database if parsed.get_backend_name() == "sqlite" else None
    missing = bool(sqlite_file) and not Path(str(sqlite_file)).exists()
    if not missing:
        engine = make_engine(url)
        try:
            missing = current_revision(engine) is None
        finally:
            engine.dispose()
    if missing and not create_database:
        typer.echo(
            f"error: no platform database at {shown}: set BGRL_DATA_DIR (or BGRL_DATABASE_URL) "
            "to the platform's, or pass --create-database to make a new one",
            err=True,
        )
        raise typer.Exit(1)
    settings.ensure_data_dir()
    upgrade_database(url)
    return make_session_factory(make_engine(url))


def create(
    email: Annotated[str, typer.Argument(help="E-mail address (the login name).")],
    admin: Annotated[bool, typer.Option("--admin", help="Make the account an admin.")] = False,
    role: Annotated[str, typer.Option(help="Role if not --admin: staff or viewer.")] = "staff",
    password: Annotated[
        str | None,
        typer.Option(help="Password (at least 12 characters); asked for when omitted."),
    ] = None,
    create_database: Annotated[
        bool,
        typer.Option("--create-database", help="Make the platform database if there is none yet."),
    ] = False,
) -> None:
    """Create an account; ``--admin`` for an administrator."""
    from services.api.accounts import create_user
    from services.core.errors import ServiceError

    sessions = _sessions(create_database)
    if password is None:
        password = typer.prompt("Password", hide_input=True, confirmation_prompt=True)
    with sessions() as db:
        try:
            user = create_user(db, email, password, "admin" if admin else role)
        except ServiceError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(1) from None
        db.commit()
        typer.echo(f"created {user.role} {user.email} (id {user.id})")


def list_users() -> None:
    """Every account: id, e-mail, role, active."""
    from sqlalchemy import select

    from services.core.db.models import User

    with _sessions()() as db:
        for user in db.scalars(select(User).order_by(User.id)):
            state = "active" if user.active else "deactivated"
            typer.echo(f"{user.id}\t{user.email}\t{user.role}\t{state}")


def set_password(
    email: Annotated[str, typer.Argument(help="E-mail address of the account.")],
    password: Annotated[
        str | None, typer.Option(help="New password; asked for when omitted.")
    ] = None,
) -> None:
    """Set an account's password (e.g. a locked-out admin) and reactivate it."""
    from sqlalchemy import select

    from services.api.accounts import check_password, normalize_email
    from services.api.accounts import set_password as give_password
    from services.core.db.models import User
    from services.core.errors import ServiceError

    sessions = _sessions()
    if password is None:
        password = typer.prompt("New password", hide_input=True, confirmation_prompt=True)
    with sessions() as db:
        try:
            check_password(password)
            user = db.scalar(select(User).where(User.email == normalize_email(email)))
        except ServiceError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(1) from None
        if user is None:
            typer.echo(f"error: no account {email}", err=True)
            raise typer.Exit(1)
        give_password(user, password)
        user.active = True
        db.commit()
        typer.echo(f"password of {user.email} set")


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``bgrl user create|list|set-password``."""
    user_app.command("create")(create)
    user_app.command("list")(list_users)
    user_app.command("set-password")(set_password)
    app.add_typer(user_app, name="user")
