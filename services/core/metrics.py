"""Prometheus metrics of a service: request latency histograms on every app, ``GET /metrics``
in Prometheus' text format, for the platform's internal token (or, on the api, an admin).

Each app has its own registry (``app.state.metrics``), so several apps in one process (tests,
``bgrl up``'s embedded mode) never share or double-count series. A service adds its own
collectors (the api: jobs by status, queue depth, live-loop latency from the database).
"""

from __future__ import annotations

import hmac
import time
from collections.abc import Callable, Iterable

from fastapi import FastAPI, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Histogram, generate_latest
from prometheus_client.registry import Collector
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.core.errors import ForbiddenError

LATENCY_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
"""Request latency buckets (s): the api's aim (p99 < 50 ms) falls between two of them."""
METRICS_PATH = "/metrics"

MetricsGuard = Callable[[Request], None]
"""Raises (403 or 401) unless the request may read the metrics."""


class _RequestMetrics:
    """Pure ASGI middleware: every HTTP request's latency, by method, route template and
    status (the template, not the path: ``/api/v1/jobs/{job_id}``, so ids make no series)."""

    def __init__(self, app: ASGIApp, histogram: Histogram) -> None:
        self.app = app
        self.histogram = histogram

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500

        async def sending(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, sending)
        finally:
            route = scope.get("route")
            template = getattr(route, "path", None) or "unmatched"
            self.histogram.labels(scope["method"], template, str(status)).observe(
                time.perf_counter() - start
            )


def token_guard(service_token: str | None) -> MetricsGuard:
    """Only a request carrying the platform's internal token (``X-Service-Token``); with no
    token configured, nobody (metrics are not public)."""

    def guard(request: Request) -> None:
        given = request.headers.get("x-service-token", "")
        if not service_token or not hmac.compare_digest(given.encode(), service_token.encode()):
            raise ForbiddenError(
                "metrics need the platform's internal token (X-Service-Token; "
                "BGRL_SERVICE_TOKEN must be set)",
                field="x-service-token",
            )

    return guard


def add_metrics(
    app: FastAPI, service: str, guard: MetricsGuard, collectors: Iterable[Collector] = ()
) -> CollectorRegistry:
    """Measure ``app``'s requests and serve ``GET /metrics`` behind ``guard``; ``collectors``
    add the service's own series. Every series carries ``service``. Returns the registry."""
    registry = CollectorRegistry(target_info={"service": service})
    histogram = Histogram(
        "bgrl_http_request_duration_seconds",
        "Time from a request's arrival to the end of its response.",
        ["method", "route", "status"],
        buckets=LATENCY_BUCKETS_S,
        registry=registry,
    )
    for collector in collectors:
        registry.register(collector)
    app.state.metrics = registry

    @app.get(METRICS_PATH, tags=["service"], response_class=Response, include_in_schema=False)
    def metrics(request: Request) -> Response:
        """Prometheus metrics of this service (internal token; on the api, admins too)."""
        guard(request)
        return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)

    app.add_middleware(_RequestMetrics, histogram=histogram)
    return registry
