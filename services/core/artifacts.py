"""The artifact store: files (recordings, checkpoints, models, results) under one root folder.

Every file is written to a temporary name inside the root, hashed (SHA-256) while it is
written, then renamed into place, so a reader never sees half a file. Paths handed out are
relative to the root, which may be a folder shared by several hosts.
"""

from __future__ import annotations

import hashlib
import os
import re
import uuid
from collections.abc import AsyncIterable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from services.core.errors import BadRequestError, PayloadTooLargeError

CHUNK_BYTES = 1024 * 1024
_UNSAFE_NAME_CHARS = re.compile(r"[^A-Za-z0-9._-]+")
_KIND = re.compile(r"^[a-z][a-z0-9_]{0,31}$")


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


class _Writer:
    """A temporary file in the store that hashes what is written and is renamed at the end."""

    def __init__(self, store: ArtifactStore, kind: str, name: str, max_bytes: int | None) -> None:
        if not _KIND.match(kind):
            raise BadRequestError(f"invalid artifact kind {kind!r}", field="kind")
        self.relpath = f"{kind}/{uuid.uuid4().hex}/{safe_filename(name)}"
        self.max_bytes = max_bytes
        self.digest = hashlib.sha256()
        self.size = 0
        tmp_dir = store.root / ".tmp"
        tmp_dir.mkdir(parents=True, exist_ok=True)
        self.tmp = tmp_dir / f"{uuid.uuid4().hex}.part"
        self.handle: BinaryIO = self.tmp.open("wb")
        self.target = store.path(self.relpath)

    def write(self, chunk: bytes) -> None:
        self.size += len(chunk)
        if self.max_bytes is not None and self.size > self.max_bytes:
            raise PayloadTooLargeError(
                f"file larger than the limit of {self.max_bytes} bytes", field="file"
            )
        self.digest.update(chunk)
        self.handle.write(chunk)

    def commit(self) -> StoredFile:
        self.handle.flush()
        os.fsync(self.handle.fileno())
        self.handle.close()
        self.target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(self.tmp, self.target)
        return StoredFile(self.relpath, self.digest.hexdigest(), self.size)

    def abort(self) -> None:
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
        self, chunks: Iterable[bytes], *, kind: str, name: str, max_bytes: int | None = None
    ) -> StoredFile:
        """Store the concatenated ``chunks``; more than ``max_bytes`` raises a 413 error."""
        writer = _Writer(self, kind, name, max_bytes)
        try:
            for chunk in chunks:
                writer.write(chunk)
            return writer.commit()
        except BaseException:
            writer.abort()
            raise

    async def put_async_stream(
        self, chunks: AsyncIterable[bytes], *, kind: str, name: str, max_bytes: int | None = None
    ) -> StoredFile:
        """:meth:`put_stream` for an async iterable (e.g. a request body as it arrives)."""
        writer = _Writer(self, kind, name, max_bytes)
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
