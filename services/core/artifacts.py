"""The artifact store: files (recordings, checkpoints, models, results) under one root folder.

Every file is written to a temporary name inside the root, hashed (SHA-256) while it is
written, then renamed into place, so a reader never sees half a file. Paths handed out are
relative to the root, which may be a folder shared by several hosts.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
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

CHUNK_BYTES = 1024 * 1024
FREE_SPACE_CHECK_BYTES = 16 * MB
"""A stream kept inside the disk's reserve is checked again after each this many bytes."""
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
        tmp_dir = store.root / ".tmp"
        tmp_dir.mkdir(parents=True, exist_ok=True)
        self.tmp = tmp_dir / f"{uuid.uuid4().hex}.part"
        self.handle: BinaryIO = self.tmp.open("wb")
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
        self.handle.close()
        self.target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(self.tmp, self.target)
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
        self.root = Path(root).resolve()
        self.root.mkdir(parents=True, exist_ok=True)

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
