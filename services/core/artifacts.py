"""The artifact store: files (recordings, checkpoints, models, results) under one root folder.

Every file is written to a temporary name inside the root (``.tmp/*.part``, locked by its
writer while it is written), hashed (SHA-256) while it is written, then renamed into place,
so a reader never sees half a file; the parts a killed process left behind are removed at
the next start (:meth:`ArtifactStore.remove_abandoned_parts`). Files are mode 600 in folders
of mode 700 (recordings are human data). Paths handed out are relative to the root, which
may be a folder shared by several hosts.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import logging
import os
import re
import time
import uuid
from collections.abc import AsyncIterable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from services.core.disk import MB, is_disk_full, require_free_space
from services.core.errors import (
    BadRequestError,
    InsufficientStorageError,
    PayloadTooLargeError,
)
from services.core.files import PRIVATE_FILE_MODE, PRIVATE_FOLDER_MODE, private_folder

logger = logging.getLogger(__name__)

CHUNK_BYTES = 1024 * 1024
FREE_SPACE_CHECK_BYTES = 16 * MB
"""A stream kept inside the disk's reserve is checked again after each this many bytes."""
TMP_FOLDER = ".tmp"
PART_SUFFIX = ".part"
NEW_SUFFIX = ".new"
"""A part's name for the instant between its creation and its lock."""
ABANDONED_AFTER_S = 60.0
"""An unlocked ``.new`` file older than this was left by a process killed in that instant."""
_UNSAFE_NAME_CHARS = re.compile(r"[^A-Za-z0-9._-]+")
_KIND = re.compile(r"^[a-z][a-z0-9_]{0,31}$")


TENSORBOARD_KIND = "tensorboard"
"""Folder kind of a training job's TensorBoard event files (:func:`job_folder`)."""


def job_folder(kind: str, job_id: str) -> str:
    """The store's folder (relative path) of a job's ``kind`` files that are rewritten as
    the job runs (its checkpoint, its TensorBoard event files)."""
    return f"{kind}/job-{job_id}"


@dataclass(frozen=True)
class StoredFile:
    """Where a stored file lives (relative to the store's root), its SHA-256 and size."""

    relpath: str
    sha256: str
    size_bytes: int


def safe_filename(name: str) -> str:
    """``name`` reduced to its last path part with only ``[A-Za-z0-9._-]`` (never empty)."""
    base = name.replace("\\", "/").rsplit("/", 1)[-1]
    cleaned = _UNSAFE_NAME_CHARS.sub("_", base).strip("._")[:120]
    return cleaned or "file"


def sha256_file(path: Path) -> str:
    """Hex SHA-256 of the file at ``path``."""
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        while chunk := handle.read(CHUNK_BYTES):
            digest.update(chunk)
    return digest.hexdigest()


@dataclass(frozen=True)
class DiskReserve:
    """Free space an incoming stream must leave on the store's disk (an upload's limit)."""

    min_free_mb: int
    """``BGRL_MIN_FREE_MB``: below it the stream is refused (507) and its file removed."""
    refusing: str = "the upload"
    """What is refused, for the message."""
    expected_bytes: int = 0
    """Bytes announced (e.g. the request's Content-Length), checked before the first one."""

    @classmethod
    def for_upload(cls, min_free_mb: int, content_length: str | None) -> DiskReserve:
        """The reserve of a request body: its ``Content-Length`` (if sent) is checked first."""
        announced = int(content_length) if content_length and content_length.isdigit() else 0
        return cls(min_free_mb=min_free_mb, refusing="the upload", expected_bytes=announced)


class _Writer:
    """A temporary file in the store that hashes what is written and is renamed at the end.

    With a :class:`DiskReserve`, the disk's free space is checked before the file is opened
    and after every :data:`FREE_SPACE_CHECK_BYTES`; a disk that fills anyway (ENOSPC) is a
    507 too. The caller aborts the writer on any error, so no part of the file is kept.
    """

    def __init__(
        self,
        store: ArtifactStore,
        kind: str,
        name: str,
        max_bytes: int | None,
        reserve: DiskReserve | None = None,
    ) -> None:
        if not _KIND.match(kind):
            raise BadRequestError(f"invalid artifact kind {kind!r}", field="kind")
        self.relpath = f"{kind}/{uuid.uuid4().hex}/{safe_filename(name)}"
        self.max_bytes = max_bytes
        self.reserve = reserve
        self.digest = hashlib.sha256()
        self.size = 0
        self.root = store.root
        self._check_free_space(reserve.expected_bytes if reserve else 0)
        self.tmp, self.handle = store.open_part()
        self.store = store
        self.target = store.path(self.relpath)

    def _check_free_space(self, incoming_bytes: int) -> None:
        if self.reserve is not None:
            require_free_space(
                self.root,
                min_free_mb=self.reserve.min_free_mb,
                refusing=self.reserve.refusing,
                incoming_bytes=incoming_bytes,
            )

    def write(self, chunk: bytes) -> None:
        before = self.size
        self.size += len(chunk)
        if self.max_bytes is not None and self.size > self.max_bytes:
            raise PayloadTooLargeError(
                f"file larger than the limit of {self.max_bytes} bytes", field="file"
            )
        if before // FREE_SPACE_CHECK_BYTES != self.size // FREE_SPACE_CHECK_BYTES:
            self._check_free_space(0)
        self.digest.update(chunk)
        try:
            self.handle.write(chunk)
        except OSError as exc:
            self._refuse_if_disk_full(exc)
            raise

    def commit(self) -> StoredFile:
        try:
            self.handle.flush()
            os.fsync(self.handle.fileno())
        except OSError as exc:
            self._refuse_if_disk_full(exc)
            raise
        self.store.make_folders(self.target.parent)
        os.replace(self.tmp, self.target)
        self.handle.close()  # after the rename: a part is never unlocked while it is one
        return StoredFile(self.relpath, self.digest.hexdigest(), self.size)

    def _refuse_if_disk_full(self, exc: OSError) -> None:
        if is_disk_full(exc):
            raise InsufficientStorageError(
                f"the disk holding {self.root} is full: nothing was stored; free some space "
                "and try again"
            ) from exc

    def abort(self) -> None:
        with contextlib.suppress(OSError):  # a full disk may fail the close's flush
            self.handle.close()
        self.tmp.unlink(missing_ok=True)


class ArtifactStore:
    """Files below ``root``, addressed by paths relative to it."""

    def __init__(self, root: Path) -> None:
        self.root = private_folder(Path(root).resolve())

    def open_part(self) -> tuple[Path, BinaryIO]:
        """A new ``.tmp/<random>.part`` (mode 600) open for writing and locked until it is
        closed, so :meth:`remove_abandoned_parts` leaves it alone while its writer lives.
        Rename it into place before closing it (every write to the store does)."""
        tmp_dir = self.root / TMP_FOLDER
        tmp_dir.mkdir(exist_ok=True, mode=PRIVATE_FOLDER_MODE)
        part = tmp_dir / f"{uuid.uuid4().hex}{PART_SUFFIX}"
        # created under another name, locked, then named a part: every part is locked for
        # as long as its writer lives (the lock, on the file, follows the rename)
        unlocked = part.with_suffix(NEW_SUFFIX)
        fd = os.open(unlocked, os.O_WRONLY | os.O_CREAT | os.O_EXCL, PRIVATE_FILE_MODE)
        fcntl.flock(fd, fcntl.LOCK_EX)
        os.replace(unlocked, part)
        return part, os.fdopen(fd, "wb")

    def make_folders(self, folder: Path) -> None:
        """Create ``folder`` (inside the root) and its missing parents, each mode 700."""
        missing = []
        while folder != self.root and not folder.is_dir():
            missing.append(folder)
            folder = folder.parent
        for path in reversed(missing):
            path.mkdir(exist_ok=True, mode=PRIVATE_FOLDER_MODE)

    def remove_abandoned_parts(self) -> int:
        """Remove the ``.tmp/*.part`` files of writers that are gone (a process killed
        mid-upload); how many. A part another process is still writing is left alone: its
        writer holds a lock on it."""
        removed = 0
        tmp_dir = self.root / TMP_FOLDER
        for part in tmp_dir.glob(f"*{PART_SUFFIX}"):
            try:
                fd = os.open(part, os.O_RDONLY)
            except FileNotFoundError:
                continue  # renamed into place or removed meanwhile
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                part.unlink(missing_ok=True)
                removed += 1
            except BlockingIOError:
                pass  # its writer is alive
            finally:
                os.close(fd)
        stale_before = time.time() - ABANDONED_AFTER_S
        for new in tmp_dir.glob(f"*{NEW_SUFFIX}"):
            with contextlib.suppress(FileNotFoundError):
                if new.stat().st_mtime < stale_before:
                    new.unlink()
                    removed += 1
        if removed:
            logger.info("removed %d abandoned partial file(s) from %s", removed, self.root)
        return removed

    def path(self, relpath: str) -> Path:
        """The absolute path of ``relpath``; refuses anything that leaves the root."""
        target = (self.root / relpath).resolve()
        if target == self.root or not target.is_relative_to(self.root):
            raise BadRequestError(f"path {relpath!r} is outside the artifact store", field="path")
        return target

    def put_file(self, src: Path, *, kind: str, name: str, move: bool = False) -> StoredFile:
        """Copy (or move, if ``move``) ``src`` into the store, hashing it on the way."""
        writer = _Writer(self, kind, name, None)
        try:
            with Path(src).open("rb") as handle:
                while chunk := handle.read(CHUNK_BYTES):
                    writer.write(chunk)
            stored = writer.commit()
        except BaseException:
            writer.abort()
            raise
        if move:
            Path(src).unlink()
        return stored

    def put_bytes(self, data: bytes, *, kind: str, name: str) -> StoredFile:
        """Store ``data`` as one file."""
        return self.put_stream([data], kind=kind, name=name)

    def put_stream(
        self,
        chunks: Iterable[bytes],
        *,
        kind: str,
        name: str,
        max_bytes: int | None = None,
        reserve: DiskReserve | None = None,
    ) -> StoredFile:
        """Store the concatenated ``chunks``; more than ``max_bytes`` raises a 413 error,
        eating into the ``reserve`` of free space a 507 (nothing is kept in either case)."""
        writer = _Writer(self, kind, name, max_bytes, reserve)
        try:
            for chunk in chunks:
                writer.write(chunk)
            return writer.commit()
        except BaseException:
            writer.abort()
            raise

    async def put_async_stream(
        self,
        chunks: AsyncIterable[bytes],
        *,
        kind: str,
        name: str,
        max_bytes: int | None = None,
        reserve: DiskReserve | None = None,
    ) -> StoredFile:
        """:meth:`put_stream` for an async iterable (e.g. a request body as it arrives)."""
        writer = _Writer(self, kind, name, max_bytes, reserve)
        try:
            async for chunk in chunks:
                writer.write(chunk)
            return writer.commit()
        except BaseException:
            writer.abort()
            raise

    def delete(self, relpath: str) -> None:
        """Remove the file (if present) and the folders it leaves empty."""
        target = self.path(relpath)
        target.unlink(missing_ok=True)
        folder = target.parent
        while folder != self.root and folder.is_relative_to(self.root):
            try:
                folder.rmdir()
            except OSError:
                break
            folder = folder.parent
