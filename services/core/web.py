"""The FastAPI skeleton every service is built on.

:func:`create_service_app` gives each service the same body-size limit (answered with a
JSON 413), the same JSON error bodies (:class:`~services.core.errors.ServiceError`,
validation errors that name the field and never echo a value JSON cannot carry, nor a
secret), a request id on every request and log line, ``GET /health``, ``GET /metrics``
(Prometheus), and ``/docs`` and ``/redoc`` whose Swagger UI and ReDoc are served by the
service itself (no CDN).
"""

from __future__ import annotations

import hmac
import json
import logging
import math
import time
import uuid
from collections.abc import Callable, Sequence
from contextlib import AbstractAsyncContextManager
from typing import Any

from fastapi import APIRouter, FastAPI, Request, params
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError, WebSocketRequestValidationError
from fastapi.responses import JSONResponse, Response
from prometheus_client.registry import Collector
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.middleware.body_limit import MAX_BODY_SIZE_SCOPE_KEY, RequestBodyLimitMiddleware
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.core.docs_pages import add_docs_pages
from services.core.errors import ServiceError
from services.core.gc_pauses import frozen_after_startup
from services.core.logging import request_id
from services.core.metrics import MetricsGuard, add_metrics, token_guard
from services.core.websockets import CLOSE_UNAUTHORIZED

log = logging.getLogger("bgrl.http")

REQUEST_ID_HEADER = "x-request-id"
SERVICE_TOKEN_HEADER = "x-service-token"


def jsonable(value: Any) -> Any:
    """``value`` with every non-finite float replaced by its name (``"nan"``, ``"inf"``) and
    every lone surrogate in text by its escape (``\\ud800``), so that it can be sent."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, dict):
        return {jsonable(str(k)): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, str):  # a lone surrogate (JSON's "\\ud800") has no UTF-8: escaped
        return value.encode("utf-8", "backslashreplace").decode("utf-8")
    if value is None or isinstance(value, int | float | bool):
        return value
    return str(value)


def _field_name(loc: Sequence[Any]) -> str:
    parts = [str(p) for p in loc if p not in ("body", "query", "path", "header", "cookie")]
    return ".".join(parts) or "body"


SECRET_FIELD_WORDS = ("password", "token", "secret", "key")
"""A field whose name holds one of these never has its submitted value echoed."""


def _echoable(value: Any, field: str) -> bool:
    """Whether a 422 may repeat the submitted ``value`` of ``field``: a single value (an
    object or list may hold a password) of a field not named like a secret."""
    lowered = field.lower()
    return not isinstance(value, dict | list | tuple) and not any(
        word in lowered for word in SECRET_FIELD_WORDS
    )


def validation_error_body(errors: Sequence[Any]) -> dict[str, Any]:
    """FastAPI's 422 list, each entry with ``field``, and inputs safe to serialise; the
    submitted value is echoed only when it is a single value of a field not named like a
    secret (never a password, a token or a whole object that may hold one).

    ``detail`` stays a list (FastAPI clients read it); ``message`` sums it up in one line.
    A body that is not JSON is named ``body`` and the message says where it breaks (FastAPI
    names the character offset as the field and says only "JSON decode error").
    """
    entries = []
    for err in errors:
        err = dict(err)
        if err.get("type") == "json_invalid":
            position = err.get("loc", ("body", 0))[-1]
            reason = (err.get("ctx") or {}).get("error", "not JSON")
            err["loc"] = ("body",)
            err["msg"] = f"the body is not valid JSON: {reason} (at character {position})"
            err.pop("input", None)
        if isinstance(err.get("msg"), str) and err["msg"].startswith(VALUE_ERROR_PREFIX):
            err["msg"] = err["msg"][len(VALUE_ERROR_PREFIX) :]
        entry = {k: jsonable(v) for k, v in err.items() if k in ("loc", "msg", "type")}
        entry["field"] = _field_name(err.get("loc", ()))
        if "input" in err and _echoable(err["input"], entry["field"]):
            text = json.dumps(jsonable(err["input"]))
            entry["input"] = jsonable(err["input"]) if len(text) <= 200 else text[:200] + "..."
        entries.append(entry)
    message = "; ".join(f"{e['field']}: {e.get('msg', 'invalid')}" for e in entries)
    return {"detail": entries, "message": message}


VALUE_ERROR_PREFIX = "Value error, "
"""What pydantic puts before the message of a validator's ValueError (dropped: the message
is written for people)."""


def _is_json(content_type: str) -> bool:
    media = content_type.split(";", 1)[0].strip().lower()
    return media == "application/json" or media.endswith("+json")


def _body_format_message(request: Request, errors: Sequence[Any]) -> str | None:
    """A plain sentence for a body sent in the wrong format, else None: JSON to a route that
    takes a form (the sign-in), or a JSON route's body sent without ``Content-Type:
    application/json`` (``curl -d`` sends a form's type, and the body is then not read as
    JSON, nor is a body without a Content-Type: pydantic's "Input should be a valid
    dictionary" says nothing of that)."""
    route = request.scope.get("route")
    body_field = getattr(route, "body_field", None)
    if body_field is None:
        return None
    content_type = request.headers.get("content-type", "")
    at_body = [e for e in errors if tuple(e.get("loc", ()))[:1] == ("body",)]
    if not at_body:
        return None
    if isinstance(body_field.field_info, params.Form):
        if _is_json(content_type):
            return (
                "this route takes a form body (application/x-www-form-urlencoded), not JSON: "
                "e.g. curl -d username=EMAIL -d password=PASSWORD"
            )
        return None
    if not _is_json(content_type) and any(tuple(e.get("loc", ())) == ("body",) for e in at_body):
        came = f"as {content_type.split(';', 1)[0]}" if content_type else "without a Content-Type"
        return (
            f"the body must be JSON sent with Content-Type: application/json (this one came "
            f"{came}); with curl: -H 'Content-Type: application/json'"
        )
    return None


def _too_large_body(limit: int | None) -> dict[str, Any]:
    detail = "request body too large"
    if limit:
        detail += f" (this endpoint accepts at most {limit} bytes)"
    return {"detail": detail, "field": "body"}


class _JsonBodyLimit:
    """Turns the body limiter's plain-text 413 into the platform's JSON error body."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        rewriting = False

        async def send_json_413(message: Message) -> None:
            nonlocal rewriting
            if message["type"] == "http.response.start" and message["status"] == 413:
                headers = dict(message.get("headers", []))
                if headers.get(b"content-type", b"").startswith(b"text/plain"):
                    rewriting = True
                    body = json.dumps(_too_large_body(scope.get(MAX_BODY_SIZE_SCOPE_KEY))).encode()
                    await send(
                        {
                            "type": "http.response.start",
                            "status": 413,
                            "headers": [
                                (b"content-type", b"application/json"),
                                (b"content-length", str(len(body)).encode()),
                            ],
                        }
                    )
                    await send({"type": "http.response.body", "body": body})
                    return
            if rewriting:
                return  # the plain-text body is replaced by the JSON one already sent
            await send(message)

        await self.app(scope, receive, send_json_413)


class _RequestId:
    """Gives every request an id (the client's ``X-Request-ID`` or a new one) and logs it."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers", []))
        given = headers.get(REQUEST_ID_HEADER.encode(), b"").decode("latin-1")
        rid = given if 0 < len(given) <= 64 and given.isprintable() else uuid.uuid4().hex[:16]
        token = request_id.set(rid)
        started = time.perf_counter()
        status_code = 0

        async def send_with_id(message: Message) -> None:
            nonlocal status_code
            if message["type"] == "http.response.start":
                status_code = message["status"]
                message.setdefault("headers", [])
                message["headers"] = [
                    *message["headers"],
                    (REQUEST_ID_HEADER.encode(), rid.encode()),
                ]
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        finally:
            if scope["type"] == "http":
                # a passed health check is a supervisor's or an orchestrator's probe, every
                # few seconds for weeks: not news
                quiet = status_code == 200 and scope.get("path") == "/health"
                log.log(
                    logging.DEBUG if quiet else logging.INFO,
                    "%s %s -> %s (%.1f ms)",
                    scope.get("method"),
                    scope.get("path"),
                    status_code or "aborted",
                    1000 * (time.perf_counter() - started),
                )
            request_id.reset(token)


class _ServiceToken:
    """Refuses every request but ``/health`` that lacks the platform's internal token."""

    def __init__(self, app: ASGIApp, token: str) -> None:
        self.app = app
        self.token = token.encode()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket") or scope.get("path") == "/health":
            await self.app(scope, receive, send)
            return
        given = dict(scope.get("headers", [])).get(SERVICE_TOKEN_HEADER.encode(), b"")
        if hmac.compare_digest(given, self.token):
            await self.app(scope, receive, send)
            return
        if scope["type"] == "websocket":
            await send(
                {"type": "websocket.close", "code": CLOSE_UNAUTHORIZED, "reason": "service token"}
            )
            return
        body = json.dumps(
            {"detail": "missing or wrong X-Service-Token", "field": SERVICE_TOKEN_HEADER}
        ).encode()
        await send(
            {
                "type": "http.response.start",
                "status": 401,
                "headers": [(b"content-type", b"application/json")],
            }
        )
        await send({"type": "http.response.body", "body": body})


def create_service_app(
    *,
    name: str,
    title: str,
    summary: str,
    version: str,
    max_body_size: int,
    lifespan: Callable[[FastAPI], AbstractAsyncContextManager[None]] | None = None,
    routers: Sequence[APIRouter] = (),
    health: Callable[[Request], dict[str, Any]] | None = None,
    service_token: str | None = None,
    metrics_guard: MetricsGuard | None = None,
    metrics_collectors: Sequence[Collector] = (),
) -> FastAPI:
    """A FastAPI app with the platform's limits, error bodies, request ids and health route;
    once ``lifespan`` has started, the objects start-up built are frozen out of the garbage
    collector's full collections (:mod:`services.core.gc_pauses`).

    ``health`` (optional) adds service-specific fields to ``GET /health``; with
    ``service_token`` every other route requires it in the ``X-Service-Token`` header.
    Every request's latency is measured and ``GET /metrics`` serves it in Prometheus' format
    (:mod:`services.core.metrics`) to whom ``metrics_guard`` lets through (default: the
    internal token only), with the series of ``metrics_collectors``.
    """
    app = FastAPI(
        title=title,
        summary=summary,
        version=version,
        lifespan=frozen_after_startup(lifespan),
        docs_url=None,  # served without a CDN by add_docs_pages
        redoc_url=None,
    )
    add_docs_pages(app)

    @app.exception_handler(ServiceError)
    async def service_error(request: Request, exc: ServiceError) -> JSONResponse:
        return JSONResponse(
            status_code=exc.status_code, content={"detail": str(exc), "field": exc.field}
        )

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> Response:
        if exc.status_code == 413:
            limit = request.scope.get(MAX_BODY_SIZE_SCOPE_KEY)
            return JSONResponse(status_code=413, content=_too_large_body(limit))
        return await http_exception_handler(request, exc)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        body = validation_error_body(exc.errors())
        plain = _body_format_message(request, exc.errors())
        if plain is not None:
            body["message"] = plain
            for entry in body["detail"]:
                entry["msg"] = plain
        return JSONResponse(status_code=422, content=body)

    @app.exception_handler(WebSocketRequestValidationError)
    async def ws_validation_error(request: Any, exc: WebSocketRequestValidationError) -> None:
        from services.core.websockets import CLOSE_BAD_REQUEST, close_reason

        body = validation_error_body(exc.errors())
        # accept first: a close before accept reaches the client as a bare HTTP 403
        await request.accept()
        await request.send_json({"type": "error", **body})
        await request.close(code=CLOSE_BAD_REQUEST, reason=close_reason(body["message"]))

    if not any(getattr(r, "path", None) == "/health" for r in routers):

        @app.get("/health", tags=["service"])
        def health_route(request: Request) -> dict[str, Any]:
            """Liveness of the service."""
            extra = health(request) if health is not None else {}
            return {"status": "ok", "service": name, **extra}

    for router in routers:
        app.include_router(router)
    add_metrics(
        app, name, metrics_guard or token_guard(service_token), collectors=metrics_collectors
    )
    # the last added is the outermost: request id, then JSON 413, then the limit itself
    app.add_middleware(RequestBodyLimitMiddleware, max_body_size=max_body_size)
    app.add_middleware(_JsonBodyLimit)
    if service_token:
        app.add_middleware(_ServiceToken, token=service_token)
    app.add_middleware(_RequestId)
    return app
