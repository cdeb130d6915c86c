"""Run the platform's Alembic migrations from code (the api and ``bgrl up`` call this)."""

from __future__ import annotations

from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Engine, text

from services.core.db.session import make_engine

MIGRATIONS_DIR = Path(__file__).with_name("migrations")
PG_MIGRATION_LOCK = 0x6267726C  # "bgrl": one migrating process at a time on PostgreSQL


def alembic_config(url: str) -> Config:
    """An Alembic configuration for ``url`` using the migrations shipped with the package."""
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    config.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    return config


def head_revision() -> str:
    """The newest migration's revision id."""
    head = ScriptDirectory.from_config(alembic_config("sqlite://")).get_current_head()
    assert head is not None
    return head


def current_revision(engine: Engine) -> str | None:
    """The revision ``engine``'s database is at (None: never migrated)."""
    with engine.connect() as connection:
        return MigrationContext.configure(connection).get_current_revision()


def upgrade_database(url: str, revision: str = "head") -> None:
    """Bring the database at ``url`` to ``revision`` (an empty database gets every table).

    Safe to call from several processes at once: on PostgreSQL an advisory lock makes the
    others wait; on SQLite the database file's write lock does.
    """
    engine = make_engine(url)
    try:
        _run(engine, url, "upgrade", revision)
    finally:
        engine.dispose()


def downgrade_database(url: str, revision: str) -> None:
    """Take the database at ``url`` back to ``revision`` (``base`` drops every table)."""
    engine = make_engine(url)
    try:
        _run(engine, url, "downgrade", revision)
    finally:
        engine.dispose()


def _run(engine: Engine, url: str, direction: str, revision: str) -> None:
    config = alembic_config(url)
    with engine.connect() as connection:
        postgres = connection.dialect.name == "postgresql"
        if postgres:
            connection.execute(text("SELECT pg_advisory_lock(:key)"), {"key": PG_MIGRATION_LOCK})
            connection.commit()
        try:
            config.attributes["connection"] = connection
            getattr(command, direction)(config, revision)
            connection.commit()
        finally:
            if postgres:
                connection.execute(
                    text("SELECT pg_advisory_unlock(:key)"), {"key": PG_MIGRATION_LOCK}
                )
                connection.commit()
