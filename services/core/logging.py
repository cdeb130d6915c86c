"""One log format for every service: standard ``logging``, request ids, optional JSON lines,
tokens redacted.

:func:`configure_logging` is called once per process (by the app factory or a CLI command);
:data:`request_id` carries the id of the HTTP request being handled, so every log line
written while handling it names it. :func:`configure_log_file` adds a size-rotated file in
``BGRL_LOG_DIR`` when that is set.
"""

from __future__ import annotations

import contextvars
import json
import logging
import os
import re
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from services.core.settings import BaseServiceSettings

request_id: contextvars.ContextVar[str] = contextvars.ContextVar("request_id", default="-")
"""Id of the request being handled in this context (``-`` outside requests)."""

TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s [%(request_id)s] %(message)s"


_SECRETS = re.compile(
    r"(?P<param>(?:access_)?token=)[^&\s\"']+"  # ?token=... in a logged URL
    r"|(?P<bearer>[Bb]earer[ .])[\w.~+/-]+=*"  # Authorization: Bearer ... / bearer.<token>
    r"|bgrl_[\w-]{16,}"  # an API token
    r"|eyJ[\w-]+\.eyJ[\w-]+\.[\w-]+"  # a JWT
)
REDACTED = "[redacted]"


def redact_secrets(text: str) -> str:
    """``text`` with every token in it replaced: ``token=`` values of URLs, bearer tokens,
    API tokens (``bgrl_...``) and JWTs."""

    def replace(match: re.Match[str]) -> str:
        return (match.group("param") or match.group("bearer") or "") + REDACTED

    return _SECRETS.sub(replace, text)


class _RedactSecrets(logging.Filter):
    """Replaces the tokens in a record's message (uvicorn logs a websocket's URL, query
    included: a client that puts ``?token=`` there must not get its token into the log)."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        redacted = redact_secrets(message)
        if redacted != message:
            record.msg, record.args = redacted, None
        return True


class _RequestIdFilter(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        if not hasattr(record, "request_id"):
            record.request_id = request_id.get()
        return True


class JsonFormatter(logging.Formatter):
    """One JSON object per line: time, level, logger, request id, message, traceback."""

    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, Any] = {
            "time": self.formatTime(record),
            "level": record.levelname,
            "logger": record.name,
            "request_id": getattr(record, "request_id", "-"),
            "message": record.getMessage(),
        }
        if record.exc_info:
            entry["traceback"] = self.formatException(record.exc_info)
        return json.dumps(entry)


_configured = False


def configure_logging(level: str = "INFO", *, json_lines: bool = False) -> None:
    """Send every logger's records to stderr in the platform's format (idempotent)."""
    global _configured
    root = logging.getLogger()
    root.setLevel(level.upper())
    if _configured:
        return
    handler = logging.StreamHandler(sys.stderr)
    handler.addFilter(_RequestIdFilter())
    handler.addFilter(_RedactSecrets())
    handler.setFormatter(JsonFormatter() if json_lines else logging.Formatter(TEXT_FORMAT))
    root.addHandler(handler)
    # uvicorn's own loggers go through the same handler and format; its access log is off:
    # every service logs each request once itself (services.core.web, with the request id)
    for name in ("uvicorn", "uvicorn.error", "uvicorn.access"):
        logging.getLogger(name).handlers.clear()
        logging.getLogger(name).propagate = True
    logging.getLogger("uvicorn.access").setLevel(logging.WARNING)
    _configured = True


LOG_FILE_MODE = 0o600
"""Log files name users and subjects: readable by the platform's user only (folder 700)."""


def configure_log_file(settings: BaseServiceSettings, name: str) -> Path | None:
    """Also write every record to ``<BGRL_LOG_DIR>/<name>.log``, rotated by size; its path.

    Nothing when ``settings.log_dir`` is unset. At ``log_max_mb`` the file becomes
    ``<name>.log.1`` (and so on up to ``log_backups``; older ones are deleted). Several
    processes may write one file (the api's uvicorn workers, the job workers): the
    handler of ``concurrent-log-handler`` takes a lock file beside it for each write and
    rotation, so no line is lost or written into a file being rotated. Idempotent.
    """
    from concurrent_log_handler import ConcurrentRotatingFileHandler

    if settings.log_dir is None:
        return None
    folder = settings.log_dir.resolve()
    path = folder / f"{name}.log"
    root = logging.getLogger()
    for handler in root.handlers:
        if isinstance(handler, ConcurrentRotatingFileHandler) and handler.baseFilename == str(path):
            return path
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    handler = ConcurrentRotatingFileHandler(
        os.fspath(path),
        maxBytes=settings.log_max_mb * 1024 * 1024,
        backupCount=settings.log_backups,
        chmod=LOG_FILE_MODE,
        encoding="utf-8",
    )
    handler.addFilter(_RequestIdFilter())
    handler.addFilter(_RedactSecrets())
    formatter = JsonFormatter() if settings.log_json else logging.Formatter(TEXT_FORMAT)
    handler.setFormatter(formatter)
    root.addHandler(handler)
    return path
