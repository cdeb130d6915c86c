"""``bgrl backup`` and ``bgrl restore``: the platform's database and files in one archive.

An online backup: the api, the services and the workers may keep running. The database is
copied first (SQLite: a WAL checkpoint, then sqlite3's backup API, one consistent snapshot
checked with ``integrity_check``; PostgreSQL: ``pg_dump`` in its custom format, one
snapshot), then the files: the data folder (``BGRL_DATA_DIR``: EEG recordings and
classifiers, the api's key, the learner's sessions...) and the artifact store
(``BGRL_ARTIFACT_DIR``). A file created after the snapshot is an extra file no row names;
artifacts are written under a temporary name and renamed, so none is caught half-written.

The archive is a tar file (mode 600: it holds human EEG data and the platform's keys) with
``manifest.json`` naming the versions, the database's kind and schema revision, and each
file's size and SHA-256. ``bgrl restore`` checks every checksum while it unpacks into a
staging folder, and refuses a data folder, artifact store or database that is not empty
unless ``--force``; restored folders are 700 and files 600.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from services.cli.backup.archive import restore_backup, write_backup
from services.cli.backup.manifest import BackupError, Target
from services.core.platform import PlatformSettings
from services.core.settings import SettingsError, load_settings


def _target() -> Target:
    try:
        return Target.from_settings(load_settings(PlatformSettings))
    except SettingsError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None


def _size(members: dict[str, Any]) -> str:
    return f"{len(members)} files, {sum(m['size'] for m in members.values()) / 2**20:.1f} MB"


def backup(
    archive: Annotated[
        Path, typer.Argument(help="The tar file to write (new; outside the data folder).")
    ],
) -> None:
    """Back up the platform online: the database (BGRL_DATABASE_URL or the SQLite file in
    BGRL_DATA_DIR), the data folder and the artifact store, into one tar file (mode 600)
    with a manifest of versions, schema revision and checksums."""
    target = _target()
    try:
        manifest = write_backup(target, archive)
    except (BackupError, OSError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from None
    database = manifest["database"]
    typer.echo(
        f"backed up {database['kind']} (schema {database['schema_revision']}) and "
        f"{_size(manifest['members'])} to {archive}"
    )


def restore(
    archive: Annotated[Path, typer.Argument(help="A tar file written by `bgrl backup`.")],
    force: Annotated[
        bool,
        typer.Option(
            "--force", help="Write over a data folder, artifact store or database holding data."
        ),
    ] = False,
) -> None:
    """Restore a backup into BGRL_DATA_DIR, BGRL_ARTIFACT_DIR and BGRL_DATABASE_URL (fresh
    ones: a folder or database holding data is refused unless --force); every file's
    checksum is checked first. Stop the platform before restoring over it."""
    from services.core.db.migrate import head_revision

    target = _target()
    try:
        manifest = restore_backup(target, archive, force=force)
    except (BackupError, OSError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from None
    revision = manifest["database"]["schema_revision"]
    typer.echo(
        f"restored {manifest['database']['kind']} (schema {revision}) and "
        f"{_size(manifest['members'])} from a backup of {manifest['created_at']} into "
        f"{target.data_dir}"
    )
    if revision != head_revision():
        typer.echo(f"`bgrl up` brings the database to the current schema {head_revision()}")


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``backup`` and ``restore`` to the ``bgrl`` command."""
    app.command("backup")(backup)
    app.command("restore")(restore)
