"""Websocket checks shared by every service (CORS does not protect websockets)."""

from __future__ import annotations

from collections.abc import Iterable
from urllib.parse import urlsplit

from starlette.requests import HTTPConnection

CLOSE_UNAUTHORIZED = 4401
"""Close code for a missing or wrong token (a user's, or the internal service token)."""
CLOSE_ORIGIN_REFUSED = 4403
"""Close code sent before ``accept`` when the Origin is not allowed."""
CLOSE_NOT_FOUND = 4404
"""Close code for an unknown resource named in the websocket's path or query."""
CLOSE_BAD_REQUEST = 4422
"""Close code for a bad query parameter or a malformed first message."""
MAX_CLOSE_REASON_BYTES = 123
"""A close frame's reason is at most 123 bytes of UTF-8 (RFC 6455, 5.5: 125-byte control
frames, 2 of them the code); a longer one is a protocol error in the server."""


def close_reason(text: str) -> str:
    """``text`` cut to fit a websocket close frame, never inside a UTF-8 character."""
    return text.encode()[:MAX_CLOSE_REASON_BYTES].decode(errors="ignore")


def origin_allowed(connection: HTTPConnection, allowed_origins: Iterable[str]) -> bool:
    """Same-host origins, configured origins, and clients that send no Origin (not browsers)."""
    origin = connection.headers.get("origin")
    if origin is None or origin in set(allowed_origins):
        return True
    host = connection.headers.get("host", "")
    return bool(host) and urlsplit(origin).netloc.lower() == host.lower()
