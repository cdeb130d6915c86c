"""``python -m services.cli.child APP --fd N``: one HTTP service process of ``bgrl up``.

Serves the ASGI app ``APP`` (``module:attribute``) with uvicorn on the listening socket
``bgrl up`` bound and handed over as file descriptor ``N``. Every process of a service is
such a child of ``bgrl up`` (the api's ``BGRL_API_WORKERS`` processes share its socket, as
uvicorn's own workers would), so each is supervised, restarted and ended with it: none is
a grandchild that could outlive a killed parent. ``--proxy-headers`` and
``--forwarded-allow-ips`` are uvicorn's options of those names.

With ``--heartbeat FILE`` the process touches ``FILE`` every second from its event loop
(uvicorn's ``callback_notify``): the supervisor tells a hung process (its loop blocked, or
the process stopped) from a healthy one, even where several processes share one port and
a health check through the port may reach a sibling.
"""

from __future__ import annotations

import argparse
import socket
from pathlib import Path

import uvicorn

GRACEFUL_SHUTDOWN_S = 5.0
"""Seconds open connections (a live page's websocket) get to finish after SIGTERM."""


def main(argv: list[str] | None = None) -> None:
    """Parse the arguments and serve until SIGTERM or SIGINT."""
    parser = argparse.ArgumentParser(prog="python -m services.cli.child", description=__doc__)
    parser.add_argument("app", help="ASGI app as module:attribute")
    parser.add_argument("--fd", type=int, required=True, help="listening socket to serve")
    parser.add_argument(
        "--proxy-headers",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="believe X-Forwarded-* headers from --forwarded-allow-ips (uvicorn's option)",
    )
    parser.add_argument(
        "--forwarded-allow-ips",
        default=None,
        help="addresses whose X-Forwarded-* headers are trusted (uvicorn's option)",
    )
    parser.add_argument(
        "--heartbeat",
        type=Path,
        default=None,
        help="file to touch every second from the event loop (the supervisor's liveness check)",
    )
    args = parser.parse_args(argv)
    sock = socket.socket(fileno=args.fd)
    heartbeat: Path | None = args.heartbeat

    async def beat() -> None:
        assert heartbeat is not None
        heartbeat.touch()

    config = uvicorn.Config(
        args.app,
        proxy_headers=args.proxy_headers,
        forwarded_allow_ips=args.forwarded_allow_ips,
        timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S,
        callback_notify=beat if heartbeat is not None else None,
        timeout_notify=0,  # uvicorn looks once a second: it beats each time
    )
    uvicorn.Server(config).run(sockets=[sock])


if __name__ == "__main__":
    main()
