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

import contextlib
import hashlib
import importlib.metadata
import io
import json
import os
import platform as python_platform
import shutil
import sqlite3
import subprocess
import tarfile
import tempfile
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path, PurePosixPath
from typing import IO, TYPE_CHECKING, Annotated, Any

import typer

from services.core.platform import PlatformSettings
from services.core.settings import SettingsError, load_settings

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


# ---------------------------------------------------------------- backup


class _HashingReader:
    """Reads at most ``size`` bytes of ``handle`` (a file that grows is cut at the size it
    had when it was listed), hashing them."""

    def __init__(self, handle: IO[bytes], size: int) -> None:
        self.handle = handle
        self.left = size
        self.digest = hashlib.sha256()

    def read(self, n: int = -1) -> bytes:
        n = self.left if n < 0 else min(n, self.left)
        chunk = self.handle.read(n)
        self.left -= len(chunk)
        self.digest.update(chunk)
        return chunk


def _tar_info(name: str, size: int, mtime: float) -> tarfile.TarInfo:
    """A regular file's header, mode 600 whatever the source's mode."""
    info = tarfile.TarInfo(name)
    info.size, info.mtime, info.mode = size, int(mtime), FILE_MODE
    return info


def _add_file(tar: tarfile.TarFile, path: Path, name: str, members: dict[str, Any]) -> bool:
    """Add ``path`` as ``name``; False if it vanished meanwhile (e.g. a deleted upload)."""
    try:
        handle = path.open("rb")
    except FileNotFoundError:
        return False
    with handle:
        stat = os.fstat(handle.fileno())
        reader = _HashingReader(handle, stat.st_size)
        tar.addfile(_tar_info(name, stat.st_size, stat.st_mtime), reader)  # type: ignore[arg-type]
    members[name] = {"size": stat.st_size, "sha256": reader.digest.hexdigest()}
    return True


def _in_progress(name: str) -> bool:
    """True for what an atomic write is still building (``.tmp`` folders, ``.x.part``,
    ``.x.tmp``) and for a restore's staging folder: never backed up."""
    hidden_work = name.startswith(".") and name.endswith((".tmp", ".part"))
    return name == ".tmp" or hidden_work or name.startswith(".restore-")


def _files_below(root: Path, skip: set[Path]) -> Iterator[tuple[Path, str]]:
    """Regular files below ``root`` (sorted; no symlinks, nothing in ``skip`` or in
    progress), with their POSIX path relative to ``root``."""
    if not root.is_dir():
        return
    for folder, subfolders, files in os.walk(root):
        here = Path(folder)
        subfolders[:] = sorted(
            d for d in subfolders if here / d not in skip and not _in_progress(d)
        )
        for name in sorted(files):
            path = here / name
            if path in skip or _in_progress(name) or path.is_symlink() or not path.is_file():
                continue
            yield path, path.relative_to(root).as_posix()


def _snapshot_sqlite(path: Path, out: Path) -> None:
    """A consistent copy of the live SQLite database at ``path`` (WAL checkpointed first)."""
    if not path.is_file():
        raise BackupError(f"no SQLite database at {path} (has the platform ever started?)")
    source = sqlite3.connect(f"{path.as_uri()}?mode=rw", uri=True, timeout=30)
    copy = sqlite3.connect(out)
    try:
        # fold the write-ahead log back into the file (PASSIVE: never waits for writers)
        source.execute("PRAGMA wal_checkpoint(PASSIVE)")
        source.backup(copy)
        copy.execute("PRAGMA journal_mode=DELETE")  # one self-contained file
        verdict = copy.execute("PRAGMA integrity_check").fetchone()[0]
        if verdict != "ok":
            raise BackupError(f"the copy of {path} fails SQLite's integrity check: {verdict}")
    finally:
        copy.close()
        source.close()


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


def _dump_postgres(url: URL, out: Path) -> str:
    """``pg_dump`` of the platform's database (or its schema) to ``out``; pg_dump's version."""
    conninfo, env, schema = _libpq(url)
    args = ["pg_dump", "--format=custom", "--no-owner", "--no-privileges", f"--file={out}"]
    if schema:
        args.append(f"--schema={schema}")
    _run_pg_tool([*args, conninfo], env)
    os.chmod(out, FILE_MODE)
    return _run_pg_tool(["pg_dump", "--version"], env).strip()


def _schema_revision(database_url: str) -> str | None:
    from services.core.db.migrate import current_revision
    from services.core.db.session import make_engine

    engine = make_engine(database_url)
    try:
        return current_revision(engine)
    finally:
        engine.dispose()


def _versions() -> dict[str, str]:
    import alembic
    import sqlalchemy

    return {
        "bgrl": importlib.metadata.version("brain-guided-rl"),
        "python": python_platform.python_version(),
        "sqlalchemy": sqlalchemy.__version__,
        "alembic": alembic.__version__,
        "sqlite": sqlite3.sqlite_version,
    }


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


def _private_file(path: Path) -> IO[bytes]:
    """``path`` opened for writing, created with mode 600 (refused if it exists)."""
    return os.fdopen(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, FILE_MODE), "wb")


def write_backup(target: Target, archive: Path) -> dict[str, Any]:
    """Back up ``target`` into the new tar file ``archive`` (mode 600); its manifest."""
    archive = archive.absolute()
    if archive.exists():
        raise BackupError(f"{archive} exists: give a new file name")
    for root in (target.data_dir, target.artifact_dir):
        if archive.is_relative_to(root):
            raise BackupError(
                f"{archive} is inside {root}, which is backed up: write the backup elsewhere "
                "(another disk is best)"
            )
    private_folders(archive.parent)
    revision = _schema_revision(target.database_url)
    if revision is None:
        raise BackupError(f"the database at {target.url.render_as_string()} has no schema")
    members: dict[str, Any] = {}
    versions = _versions()
    part = archive.with_name(f".{archive.name}.{uuid.uuid4().hex[:8]}.part")
    try:
        with (
            tempfile.TemporaryDirectory(dir=archive.parent, prefix=".bgrl-backup-") as staging,
            _private_file(part) as handle,
            tarfile.open(fileobj=handle, mode="w", format=tarfile.PAX_FORMAT) as tar,
        ):
            skip = {target.artifact_dir, *(target.data_dir / f for f in SKIPPED_DATA_FOLDERS)}
            if target.log_dir is not None:
                skip.add(target.log_dir)
            if target.is_sqlite:
                db_path = target.sqlite_path
                skip |= {Path(f"{db_path}{end}") for end in ("", "-wal", "-shm", "-journal")}
                copy = Path(staging) / "bgrl.db"
                _snapshot_sqlite(db_path, copy)
                _add_file(tar, copy, SQLITE_MEMBER, members)
                database = {"kind": "sqlite", "member": SQLITE_MEMBER}
            else:
                dump = Path(staging) / "postgresql.dump"
                versions["pg_dump"] = _dump_postgres(target.url, dump)
                _add_file(tar, dump, POSTGRES_MEMBER, members)
                database = {"kind": "postgresql", "member": POSTGRES_MEMBER}
            for path, rel in _files_below(target.data_dir, skip):
                _add_file(tar, path, DATA_PREFIX + rel, members)
            for path, rel in _files_below(target.artifact_dir, set()):
                _add_file(tar, path, ARTIFACTS_PREFIX + rel, members)
            now = datetime.now(UTC)
            manifest = {
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "created_at": now.isoformat(timespec="seconds"),
                "versions": versions,
                "database": {**database, "schema_revision": revision},
                "source": {
                    "data_dir": str(target.data_dir),
                    "artifact_dir": str(target.artifact_dir),
                },
                "members": members,
            }
            body = json.dumps(manifest, indent=2).encode()
            tar.addfile(_tar_info(MANIFEST, len(body), now.timestamp()), io.BytesIO(body))
        with part.open("rb") as done:
            os.fsync(done.fileno())
        os.replace(part, archive)
    finally:
        part.unlink(missing_ok=True)
    return manifest


# ---------------------------------------------------------------- restore


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


def _check_revision(revision: str | None) -> str:
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


def _not_empty(folder: Path) -> bool:
    return folder.is_dir() and any(folder.iterdir())


def _postgres_has_tables(url: URL) -> bool:
    from sqlalchemy import text

    from services.core.db.session import make_engine

    engine = make_engine(url.render_as_string(hide_password=False))
    try:
        with engine.connect() as connection:
            found = connection.execute(text("SELECT to_regclass('alembic_version')")).scalar()
    finally:
        engine.dispose()
    return found is not None


def _check_target(target: Target, kind: str, force: bool) -> None:
    """Refuse a database of the other kind, and a target holding data unless ``force``."""
    wanted = "sqlite" if target.is_sqlite else "postgresql"
    if kind != wanted:
        raise BackupError(
            f"the backup holds a {kind} database but BGRL_DATABASE_URL points to {wanted}: "
            f"set BGRL_DATABASE_URL to a {kind} database to restore into"
        )
    if force:
        return
    occupied = [str(f) for f in (target.data_dir, target.artifact_dir) if _not_empty(f)]
    if target.is_sqlite and target.sqlite_path.exists():
        occupied.append(str(target.sqlite_path))
    if not target.is_sqlite and _postgres_has_tables(target.url):
        occupied.append(f"the database {target.url.render_as_string()}")
    if occupied:
        raise BackupError(
            f"already holding data: {', '.join(dict.fromkeys(occupied))}; restore into a fresh "
            "data folder and database, or give --force to write over them"
        )


def _member_destination(name: str, target: Target, database_member: str) -> tuple[Path, str]:
    """(root, relative path) a manifest member is restored to; refuses unsafe names."""
    rel = PurePosixPath(name)
    if rel.is_absolute() or ".." in rel.parts:
        raise BackupError(f"the archive names an unsafe path {name!r}")
    if name == database_member:
        return target.data_dir, ".database"
    for prefix, root in ((DATA_PREFIX, target.data_dir), (ARTIFACTS_PREFIX, target.artifact_dir)):
        if name.startswith(prefix) and len(name) > len(prefix):
            return root, name[len(prefix) :]
    raise BackupError(f"the archive holds an unexpected member {name!r}")


def _extract_checked(
    tar: tarfile.TarFile, member: tarfile.TarInfo, expected: dict[str, Any], out: Path
) -> None:
    """Write ``member`` to ``out`` (mode 600), checking its size and SHA-256."""
    handle = tar.extractfile(member) if member.isfile() else None
    if handle is None:
        raise BackupError(f"the archive's {member.name} is not a file")
    private_folders(out.parent)
    digest, size = hashlib.sha256(), 0
    with _private_file(out) as dst:
        while chunk := handle.read(CHUNK_BYTES):
            digest.update(chunk)
            size += len(chunk)
            dst.write(chunk)
    if size != expected["size"] or digest.hexdigest() != expected["sha256"]:
        raise BackupError(
            f"the archive's {member.name} does not match its checksum: the backup is damaged"
        )


def _restore_postgres(url: URL, dump: Path, force: bool) -> None:
    conninfo, env, _schema = _libpq(url)
    args = ["pg_restore", "--no-owner", "--no-privileges", "--exit-on-error"]
    args += ["--single-transaction", f"--dbname={conninfo}"]
    if force:
        args += ["--clean", "--if-exists"]
    _run_pg_tool([*args, str(dump)], env)


@contextlib.contextmanager
def _open_archive(archive: Path) -> Iterator[tarfile.TarFile]:
    if not archive.is_file():
        raise BackupError(f"no backup at {archive}")
    try:
        tar = tarfile.open(archive, mode="r:*")  # noqa: SIM115 - closed below
    except tarfile.TarError as exc:
        raise BackupError(f"{archive} is not a tar archive: {exc}") from None
    with tar:
        yield tar


def restore_backup(target: Target, archive: Path, *, force: bool = False) -> dict[str, Any]:
    """Restore ``archive`` into ``target``; its manifest.

    Every file is unpacked below a staging folder in its destination root and checked
    against the manifest before anything is moved into place, so a damaged archive
    changes nothing.
    """
    with _open_archive(archive) as tar:
        manifest = read_manifest(tar, archive)
        database = manifest["database"]
        revision = _check_revision(database.get("schema_revision"))
        _check_target(target, database["kind"], force)
        expected: dict[str, Any] = manifest["members"]
        if database["member"] not in expected:
            raise BackupError(f"{archive} holds no database")
        roots = {target.data_dir, target.artifact_dir}
        for root in roots:
            private_folders(root)
        staging = {root: root / f".restore-{uuid.uuid4().hex[:8]}" for root in roots}
        try:
            placed: list[tuple[Path, Path, str]] = []
            seen: set[str] = set()
            for member in tar:
                if member.name == MANIFEST:
                    continue
                if member.name not in expected:
                    raise BackupError(f"the archive holds {member.name!r}, not in its manifest")
                root, rel = _member_destination(member.name, target, database["member"])
                private_folders(staging[root])
                _extract_checked(tar, member, expected[member.name], staging[root] / rel)
                placed.append((staging[root] / rel, root, rel))
                seen.add(member.name)
            missing = sorted(set(expected) - seen)
            if missing:
                raise BackupError(f"the archive lacks {len(missing)} files, e.g. {missing[0]}")
            for staged, root, rel in placed:
                if rel == ".database":
                    _place_database(target, staged, force)
                else:
                    _move_into(staged, root / rel)
        finally:
            for folder in staging.values():
                shutil.rmtree(folder, ignore_errors=True)
    manifest["database"]["schema_revision"] = revision
    return manifest


def _place_database(target: Target, staged: Path, force: bool) -> None:
    if not target.is_sqlite:
        _restore_postgres(target.url, staged, force)
        return
    path = target.sqlite_path
    private_folders(path.parent)
    for end in ("-wal", "-shm", "-journal"):  # a stale log must not replay onto the copy
        Path(f"{path}{end}").unlink(missing_ok=True)
    _move_into(staged, path)


def _move_into(staged: Path, final: Path) -> None:
    """Move a staged file to ``final``, creating its folders with mode 700."""
    private_folders(final.parent)
    if final.is_dir():
        raise BackupError(f"{final} is a folder; the backup has a file there")
    shutil.move(staged, final)


# ---------------------------------------------------------------- commands


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
