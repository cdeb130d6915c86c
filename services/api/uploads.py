"""Streamed uploads: a request body (raw or multipart) goes to the artifact store as it arrives.

Nothing is buffered in memory beyond one chunk: the SHA-256 is computed while the bytes are
written, and a body over the limit is refused (413) with the partial file removed.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import PurePosixPath

from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import Request

from services.core.artifacts import ArtifactStore, DiskReserve, StoredFile
from services.core.errors import BadRequestError, UnsupportedMediaError

RECORDING_SUFFIXES = (".bdf", ".edf", ".fif", ".set", ".xdf", ".zip")
"""File types the EEG pipeline reads (``.zip``: a BrainVision .vhdr/.vmrk/.eeg set or an
EEGLAB .set/.fdt dataset; checked
again, from the bytes, when it validates)."""
FILE_FIELD = "file"


def check_recording_name(filename: str) -> str:
    """The file's last path part; 415 unless it ends in a recording suffix."""
    name = PurePosixPath(filename.replace("\\", "/")).name
    if not name or len(name) > 255:
        raise BadRequestError("give the recording's file name", field="filename")
    if any(ord(char) < 32 or ord(char) == 127 for char in name):
        raise BadRequestError(
            f"the file name {name!r} has control characters; rename the file", field="filename"
        )
    if PurePosixPath(name).suffix.lower() not in RECORDING_SUFFIXES:
        raise UnsupportedMediaError(
            f"{name!r} is not a recording; send one of {', '.join(RECORDING_SUFFIXES)}",
            field="filename",
        )
    return name


class _MultipartFile:
    """The ``file`` part of a multipart body, streamed: headers first, then its bytes."""

    def __init__(self, request: Request, boundary: bytes) -> None:
        self.request = request
        self.body = request.stream()
        self.filename: str | None = None
        self._field = b""
        self._value = b""
        self._headers: dict[bytes, bytes] = {}
        self._in_file = False
        self._file_done = False
        self._buffer: list[bytes] = []
        self.parser = MultipartParser(
            boundary,
            {
                "on_part_begin": self._part_begin,
                "on_header_field": self._header_field,
                "on_header_value": self._header_value,
                "on_header_end": self._header_end,
                "on_headers_finished": self._headers_finished,
                "on_part_data": self._part_data,
                "on_part_end": self._part_end,
            },
        )

    def _part_begin(self) -> None:
        self._headers = {}

    def _header_field(self, data: bytes, start: int, end: int) -> None:
        self._field += data[start:end]

    def _header_value(self, data: bytes, start: int, end: int) -> None:
        self._value += data[start:end]

    def _header_end(self) -> None:
        self._headers[self._field.lower()] = self._value
        self._field = self._value = b""

    def _headers_finished(self) -> None:
        _, options = parse_options_header(self._headers.get(b"content-disposition", b""))
        if options.get(b"name") == FILE_FIELD.encode() and self.filename is None:
            self.filename = options.get(b"filename", b"").decode("utf-8", "replace")
            self._in_file = True

    def _part_data(self, data: bytes, start: int, end: int) -> None:
        if self._in_file:
            self._buffer.append(data[start:end])

    def _part_end(self) -> None:
        if self._in_file:
            self._in_file = False
            self._file_done = True

    async def _feed_next(self) -> bool:
        try:
            chunk = await self.body.__anext__()
        except StopAsyncIteration:
            return False
        try:
            self.parser.write(chunk)
        except Exception as exc:  # python-multipart raises its own errors for bad bodies
            raise BadRequestError(f"malformed multipart body: {exc}", field="body") from None
        return True

    async def start(self) -> str:
        """Read until the ``file`` part's headers; its file name."""
        while self.filename is None:
            if not await self._feed_next():
                raise BadRequestError(
                    f"the multipart body has no '{FILE_FIELD}' part", field=FILE_FIELD
                )
        return self.filename

    async def chunks(self) -> AsyncIterator[bytes]:
        """The file part's bytes as they arrive."""
        while True:
            while self._buffer:
                yield self._buffer.pop(0)
            if self._file_done:
                return
            if not await self._feed_next():
                raise BadRequestError("the multipart body ended inside the file", field="body")


async def receive_recording(
    request: Request,
    store: ArtifactStore,
    *,
    filename: str | None,
    max_bytes: int,
    min_free_mb: int,
) -> tuple[StoredFile, str]:
    """Store the uploaded recording; the stored file and its (checked) name.

    ``multipart/form-data`` with a ``file`` part, or the raw file as the body with
    ``?filename=``. A disk that would keep less than ``min_free_mb`` free is a 507 (the
    partial file removed).
    """
    content_type, options = parse_options_header(request.headers.get("content-type", ""))
    if content_type == b"multipart/form-data":
        boundary = options.get(b"boundary")
        if not boundary:
            raise BadRequestError("multipart body without a boundary", field="content-type")
        upload = _MultipartFile(request, boundary)
        part_name = await upload.start()
        name = check_recording_name(filename or part_name)
        stream = upload.chunks()
    else:
        if not filename:
            raise BadRequestError(
                "give ?filename= with a raw body, or send multipart/form-data with a 'file' part",
                field="filename",
            )
        name = check_recording_name(filename)
        stream = request.stream()
    reserve = DiskReserve.for_upload(min_free_mb, request.headers.get("content-length"))
    stored = await store.put_async_stream(
        stream, kind="recording", name=name, max_bytes=max_bytes, reserve=reserve
    )
    if stored.size_bytes == 0:
        store.delete(stored.relpath)
        raise BadRequestError("the recording is empty", field=FILE_FIELD)
    return stored, name
