"""The backup archive: writing it (the database's snapshot, then the files, then the
manifest) and restoring it (every checksum checked in a staging folder first)."""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
import tarfile
import tempfile
import uuid
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path, PurePosixPath
from typing import IO, Any

from services.cli.backup.manifest import (
    ARTIFACTS_PREFIX,
    CHUNK_BYTES,
    DATA_PREFIX,
    FILE_MODE,
    FORMAT,
    FORMAT_VERSION,
    MANIFEST,
    POSTGRES_MEMBER,
    SKIPPED_DATA_FOLDERS,
    SQLITE_MEMBER,
    BackupError,
    Target,
    check_revision,
    move_into,
    private_file,
    private_folders,
    read_manifest,
    schema_revision,
    versions_now,
)
from services.cli.backup.postgres import dump_postgres, postgres_has_tables, restore_postgres
from services.cli.backup.sqlite import place_sqlite, snapshot_sqlite


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
    revision = schema_revision(target.database_url)
    if revision is None:
        raise BackupError(f"the database at {target.url.render_as_string()} has no schema")
    members: dict[str, Any] = {}
    versions = versions_now()
    part = archive.with_name(f".{archive.name}.{uuid.uuid4().hex[:8]}.part")
    try:
        with (
            tempfile.TemporaryDirectory(dir=archive.parent, prefix=".bgrl-backup-") as staging,
            private_file(part) as handle,
            tarfile.open(fileobj=handle, mode="w", format=tarfile.PAX_FORMAT) as tar,
        ):
            skip = {target.artifact_dir, *(target.data_dir / f for f in SKIPPED_DATA_FOLDERS)}
            if target.log_dir is not None:
                skip.add(target.log_dir)
            if target.is_sqlite:
                db_path = target.sqlite_path
                skip |= {Path(f"{db_path}{end}") for end in ("", "-wal", "-shm", "-journal")}
                copy = Path(staging) / "bgrl.db"
                snapshot_sqlite(db_path, copy)
                _add_file(tar, copy, SQLITE_MEMBER, members)
                database = {"kind": "sqlite", "member": SQLITE_MEMBER}
            else:
                dump = Path(staging) / "postgresql.dump"
                versions["pg_dump"] = dump_postgres(target.url, dump)
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


def _not_empty(folder: Path) -> bool:
    return folder.is_dir() and any(folder.iterdir())


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
    if not target.is_sqlite and postgres_has_tables(target.url):
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
    with private_file(out) as dst:
        while chunk := handle.read(CHUNK_BYTES):
            digest.update(chunk)
            size += len(chunk)
            dst.write(chunk)
    if size != expected["size"] or digest.hexdigest() != expected["sha256"]:
        raise BackupError(
            f"the archive's {member.name} does not match its checksum: the backup is damaged"
        )


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
        revision = check_revision(database.get("schema_revision"))
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
                    move_into(staged, root / rel)
        finally:
            for folder in staging.values():
                shutil.rmtree(folder, ignore_errors=True)
    manifest["database"]["schema_revision"] = revision
    return manifest


def _place_database(target: Target, staged: Path, force: bool) -> None:
    if target.is_sqlite:
        place_sqlite(target, staged)
    else:
        restore_postgres(target.url, staged, force)
