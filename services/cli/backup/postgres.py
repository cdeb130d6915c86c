"""PostgreSQL: ``pg_dump`` (custom format, one snapshot) and ``pg_restore`` of the platform's
database or of the schema its URL's ``search_path`` names."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path
from typing import TYPE_CHECKING

from services.cli.backup.manifest import FILE_MODE, BackupError

if TYPE_CHECKING:
    from sqlalchemy import URL


def _libpq(url: URL) -> tuple[str, dict[str, str], str | None]:
    """The libpq URI of a SQLAlchemy PostgreSQL URL (no password: that goes in
    ``PGPASSWORD``), the environment for pg_dump/pg_restore and the schema named by a
    ``search_path`` option (None: the whole database)."""
    env = {**os.environ}
    if url.password:
        env["PGPASSWORD"] = str(url.password)
    plain = url.set(drivername="postgresql", password=None)
    options = url.query.get("options", ())
    schema = None
    for option in [options] if isinstance(options, str) else options:
        for part in option.split():
            key, _, value = part.removeprefix("-c").partition("=")
            if key == "search_path" and value:
                schema = value.split(",")[0].strip()
    return plain.render_as_string(hide_password=False), env, schema


def _run_pg_tool(args: list[str], env: dict[str, str]) -> str:
    """Run pg_dump/pg_restore; its first error line as :class:`BackupError`."""
    tool = args[0]
    if shutil.which(tool) is None:
        raise BackupError(
            f"{tool} is not installed: install PostgreSQL's client tools "
            "(Debian: apt-get install postgresql-client) in the server's major version"
        )
    result = subprocess.run(args, env=env, capture_output=True, text=True, check=False)
    if result.returncode != 0:
        lines = [line for line in result.stderr.splitlines() if line.strip()]
        raise BackupError(f"{tool} failed: {lines[0] if lines else f'exit {result.returncode}'}")
    return result.stdout


def dump_postgres(url: URL, out: Path) -> str:
    """``pg_dump`` of the platform's database (or its schema) to ``out``; pg_dump's version."""
    conninfo, env, schema = _libpq(url)
    args = ["pg_dump", "--format=custom", "--no-owner", "--no-privileges", f"--file={out}"]
    if schema:
        args.append(f"--schema={schema}")
    _run_pg_tool([*args, conninfo], env)
    os.chmod(out, FILE_MODE)
    return _run_pg_tool(["pg_dump", "--version"], env).strip()


def restore_postgres(url: URL, dump: Path, force: bool) -> None:
    conninfo, env, _schema = _libpq(url)
    args = ["pg_restore", "--no-owner", "--no-privileges", "--exit-on-error"]
    args += ["--single-transaction", f"--dbname={conninfo}"]
    if force:
        args += ["--clean", "--if-exists"]
    _run_pg_tool([*args, str(dump)], env)


def postgres_has_tables(url: URL) -> bool:
    from sqlalchemy import text

    from services.core.db.session import make_engine

    engine = make_engine(url.render_as_string(hide_password=False))
    try:
        with engine.connect() as connection:
            found = connection.execute(text("SELECT to_regclass('alembic_version')")).scalar()
    finally:
        engine.dispose()
    return found is not None
