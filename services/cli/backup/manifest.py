"""What every backup shares: the archive's format and manifest, the target folders and
database, and private files and folders (700/600)."""

from __future__ import annotations

import importlib.metadata
import json
import os
import platform as python_platform
import shutil
import sqlite3
import tarfile
from dataclasses import dataclass
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

from services.core.platform import PlatformSettings

if TYPE_CHECKING:  # SQLAlchemy is in the api and worker installs, not the client's
    from sqlalchemy import URL

FORMAT = "bgrl-backup"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
SQLITE_MEMBER = "database/bgrl.db"
POSTGRES_MEMBER = "database/postgresql.dump"
DATA_PREFIX = "data/"
ARTIFACTS_PREFIX = "artifacts/"
SKIPPED_DATA_FOLDERS = ("broker", "eeg/incoming")
"""Folders of the data folder not backed up: the embedded broker's messages (the jobs'
rows are the truth: the reaper sends queued jobs again) and uploads still arriving."""
CHUNK_BYTES = 1024 * 1024
FILE_MODE = 0o600
FOLDER_MODE = 0o700


class BackupError(Exception):
    """A backup or restore that cannot go on; the message is one line for the user."""


@dataclass(frozen=True)
class Target:
    """Where the platform keeps its database and files (from the ``BGRL_*`` settings)."""

    database_url: str
    data_dir: Path
    artifact_dir: Path
    log_dir: Path | None = None
    """``BGRL_LOG_DIR``: not backed up when it lies in the data folder."""

    @classmethod
    def from_settings(cls, settings: PlatformSettings) -> Target:
        return cls(
            settings.resolved_database_url,
            settings.data_dir.resolve(),
            settings.resolved_artifact_dir,
            settings.log_dir.resolve() if settings.log_dir is not None else None,
        )

    @property
    def url(self) -> URL:
        from sqlalchemy import make_url

        return make_url(self.database_url)

    @property
    def is_sqlite(self) -> bool:
        return self.url.get_backend_name() == "sqlite"

    @property
    def sqlite_path(self) -> Path:
        if not self.url.database or self.url.database == ":memory:":
            raise BackupError(f"{self.url.render_as_string()} is not a SQLite file")
        return Path(self.url.database).resolve()


def versions_now() -> dict[str, str]:
    import alembic
    import sqlalchemy

    return {
        "bgrl": importlib.metadata.version("brain-guided-rl"),
        "python": python_platform.python_version(),
        "sqlalchemy": sqlalchemy.__version__,
        "alembic": alembic.__version__,
        "sqlite": sqlite3.sqlite_version,
    }


def schema_revision(database_url: str) -> str | None:
    from services.core.db.migrate import current_revision
    from services.core.db.session import make_engine

    engine = make_engine(database_url)
    try:
        return current_revision(engine)
    finally:
        engine.dispose()


def read_manifest(tar: tarfile.TarFile, archive: Path) -> dict[str, Any]:
    """The archive's manifest, checked to be one of ours."""
    try:
        handle = tar.extractfile(MANIFEST)
        manifest = json.loads(handle.read()) if handle is not None else None
    except (KeyError, ValueError):
        manifest = None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise BackupError(f"{archive} is not a backup made by `bgrl backup` (no manifest)")
    if manifest.get("format_version") != FORMAT_VERSION:
        raise BackupError(
            f"{archive} is a backup of format {manifest.get('format_version')}; this bgrl "
            f"reads format {FORMAT_VERSION}"
        )
    return manifest


def check_revision(revision: str | None) -> str:
    """``revision`` if this code's migrations know it (a newer bgrl's backup is refused)."""
    from alembic.script import ScriptDirectory

    from services.core.db.migrate import alembic_config

    scripts = ScriptDirectory.from_config(alembic_config("sqlite://"))
    try:
        known = revision is not None and scripts.get_revision(revision) is not None
    except Exception:
        known = False
    if not known:
        raise BackupError(
            f"the backup's database is at schema revision {revision!r}, which this bgrl "
            "does not know: restore it with the bgrl version that made it (or newer)"
        )
    assert revision is not None
    return revision


def private_folders(folder: Path) -> None:
    """Create ``folder`` and each missing parent with mode 700 (``Path.mkdir(parents=True)``
    gives the parents the default mode); folders that exist are left as they are."""
    missing = []
    while not folder.exists():
        missing.append(folder)
        folder = folder.parent
    for path in reversed(missing):
        path.mkdir(mode=FOLDER_MODE, exist_ok=True)
        os.chmod(path, FOLDER_MODE)  # whatever the umask


def private_file(path: Path) -> IO[bytes]:
    """``path`` opened for writing, created with mode 600 (refused if it exists)."""
    return os.fdopen(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, FILE_MODE), "wb")


def move_into(staged: Path, final: Path) -> None:
    """Move a staged file to ``final``, creating its folders with mode 700."""
    private_folders(final.parent)
    if final.is_dir():
        raise BackupError(f"{final} is a folder; the backup has a file there")
    shutil.move(staged, final)
