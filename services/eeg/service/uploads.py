"""Receiving a recording upload: the raw body or the ``file`` field of a multipart form.

Either way the file's bytes are streamed to the artifact store's temporary area as they
arrive (never held in memory), hashed on the way and checked against the size limit.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from dataclasses import dataclass

from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import ClientDisconnect, Request

from services.core.artifacts import ArtifactStore, DiskReserve, StoredFile
from services.core.errors import BadRequestError
from services.eeg.service.errors import UploadAbortedError

logger = logging.getLogger(__name__)

FILE_FIELD = "file"
"""Name of the multipart form field that carries the recording."""
INCOMING_KIND = "incoming"
"""Artifact kind (folder) of uploads still being received or validated."""

UPLOAD_OPENAPI = {
    "requestBody": {
        "required": True,
        "description": "The recording (BDF, EDF, FIF, XDF, an EEGLAB .set, or a zip of a "
        "BrainVision .vhdr/.vmrk/.eeg set or of an EEGLAB .set and its .fdt): either a "
        "multipart form with the "
        "file in the field `file`, or the file's bytes as the body (any other content type; "
        "name it with `?filename=`).",
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": [FILE_FIELD],
                    "properties": {FILE_FIELD: {"type": "string", "format": "binary"}},
                }
            },
            "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
        },
    }
}
"""OpenAPI description of the two accepted bodies (so ``/docs`` can upload a file)."""


@dataclass(frozen=True)
class Upload:
    """A received file in the artifact store's ``incoming`` area."""

    stored: StoredFile
    filename: str | None
    """Name the client gave (multipart ``filename`` or ``?filename=``), if any."""


class _MultipartFile:
    """Streams the ``file`` field out of a multipart body; any other field is refused."""

    def __init__(self, content_type: str) -> None:
        _, options = parse_options_header(content_type)
        boundary = options.get(b"boundary")
        if not boundary:
            raise BadRequestError("multipart body without a boundary", field="body")
        self.filename: str | None = None
        self._found = False
        self._in_file = False
        self._pending: list[bytes] = []
        self._header_name = b""
        self._header_value = b""
        self._disposition = b""
        self._parser = MultipartParser(
            boundary,
            {
                "on_part_begin": self._on_part_begin,
                "on_header_field": self._on_header_field,
                "on_header_value": self._on_header_value,
                "on_header_end": self._on_header_end,
                "on_headers_finished": self._on_headers_finished,
                "on_part_data": self._on_part_data,
                "on_part_end": self._on_part_end,
            },
        )

    def _on_part_begin(self) -> None:
        self._disposition = b""

    def _on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._header_name += data[start:end]

    def _on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._header_value += data[start:end]

    def _on_header_end(self) -> None:
        if self._header_name.lower() == b"content-disposition":
            self._disposition = self._header_value
        self._header_name = self._header_value = b""

    def _on_headers_finished(self) -> None:
        _, options = parse_options_header(self._disposition)
        name = options.get(b"name", b"").decode("utf-8", "replace")
        if name != FILE_FIELD:
            raise BadRequestError(
                f"unexpected form field {name!r}; send the recording in the field {FILE_FIELD!r}",
                field=name or "body",
            )
        if self._found:
            raise BadRequestError("send one recording per upload", field=FILE_FIELD)
        self._found = self._in_file = True
        if b"filename" in options:
            self.filename = options[b"filename"].decode("utf-8", "replace")

    def _on_part_data(self, data: bytes, start: int, end: int) -> None:
        if self._in_file:
            self._pending.append(data[start:end])

    def _on_part_end(self) -> None:
        self._in_file = False

    async def file_chunks(self, body: AsyncIterator[bytes]) -> AsyncIterator[bytes]:
        """The bytes of the ``file`` field, as the body arrives."""
        try:
            async for chunk in body:
                self._parser.write(chunk)
                for piece in self._pending:
                    yield piece
                self._pending.clear()
            self._parser.finalize()
        except MultipartParseError as exc:
            raise BadRequestError(f"malformed multipart body: {exc}", field="body") from exc
        for piece in self._pending:
            yield piece
        if not self._found:
            raise BadRequestError(
                f"multipart body without the field {FILE_FIELD!r}", field=FILE_FIELD
            )


async def receive_upload(
    request: Request,
    store: ArtifactStore,
    *,
    filename: str | None,
    max_bytes: int,
    min_free_mb: int,
) -> Upload:
    """Stream the uploaded recording into ``store`` (kind ``incoming``).

    Raises a 422 for an empty or malformed body, a 413 over ``max_bytes``, a 507 when the
    disk would keep less than ``min_free_mb`` free (nothing kept) and
    :class:`UploadAbortedError` when the client goes away mid-upload (logged as one
    warning line).
    """
    content_type = request.headers.get("content-type", "")
    multipart = (
        _MultipartFile(content_type) if content_type.startswith("multipart/form-data") else None
    )
    chunks = multipart.file_chunks(request.stream()) if multipart else request.stream()
    try:
        stored = await store.put_async_stream(
            chunks,
            kind=INCOMING_KIND,
            name="upload",
            max_bytes=max_bytes,
            reserve=DiskReserve.for_upload(min_free_mb, request.headers.get("content-length")),
        )
    except ClientDisconnect:
        logger.warning(
            "upload aborted by the client (%s); nothing was stored",
            request.headers.get("content-length", "unknown") + " bytes announced",
        )
        raise UploadAbortedError("the upload was aborted before the body was complete") from None
    if stored.size_bytes == 0:
        store.delete(stored.relpath)
        raise BadRequestError(
            "empty upload: send the file as the body or in the multipart field 'file'",
            field=FILE_FIELD,
        )
    name = multipart.filename if multipart and multipart.filename else filename
    return Upload(stored=stored, filename=name)
