"""Hot reads: a GET route answered before FastAPI's routing and dependency solving.

FastAPI spends about a third of a lean list request's CPU matching the path against the
app's routes, solving the route's dependencies and validating its query parameters.
:class:`HotReads` answers a GET to one of a few paths with that path's hot handler, which
takes only a request whose every parameter is plainly valid (it parses them itself) and
answers it as the route would: the route's own code, the same bytes and headers. For any
other request (a parameter it does not know or that needs pydantic's judgement, a missing
or refused token) the handler returns None and the app answers as usual, with its 401 or
422, so errors and the OpenAPI schema (the route stays registered) are unchanged.

It sits inside the platform's middleware (request id, access log, body limit) and outside
FastAPI's exception handlers: a hot handler declines what would raise a handled error.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping

from fastapi import FastAPI, Request, Response
from starlette.middleware import Middleware
from starlette.types import ASGIApp, Receive, Scope, Send

HotRead = Callable[[Request], Awaitable[Response | None]]
"""A hot handler: the route's response to the request, or None to leave it to the route."""


class HotReads:
    """Pure ASGI middleware: a GET to a path of ``routes`` goes to its hot handler first."""

    def __init__(self, app: ASGIApp, routes: Mapping[str, HotRead]) -> None:
        self.app = app
        self.routes = dict(routes)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (
            scope["type"] == "http"
            and scope["method"] == "GET"
            and not scope.get("root_path")  # the path is the route's path
            and (hot := self.routes.get(scope["path"])) is not None
        ):
            response = await hot(Request(scope, receive))
            if response is not None:
                await response(scope, receive, send)
                return
        await self.app(scope, receive, send)


def add_hot_reads(app: FastAPI, routes: Mapping[str, HotRead]) -> None:
    """Serve ``routes`` (path -> hot handler) through :class:`HotReads`, as the innermost
    of the app's own middleware (``add_middleware`` would make it the outermost, before
    the request id and the body limit)."""
    app.user_middleware.append(Middleware(HotReads, routes=routes))
