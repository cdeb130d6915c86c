"""The sim service: sessions over HTTP, frames over a websocket, action markers over LSL.

Run with ``uvicorn services.sim.app:app --port 8001`` (or ``bgrl serve``); configuration
comes from ``BGRL_SIM_*`` environment variables (:class:`SimSettings`). Endpoints are
documented in ``docs/sim-service.md`` and at ``/docs``. The app is built on the platform's
skeleton (:func:`services.core.web.create_service_app`): JSON 413 and 422 bodies naming the
field, request ids, ``GET /health``.
"""

from __future__ import annotations

import socket
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from services.core.logging import configure_log_file, configure_logging
from services.core.settings import load_settings
from services.core.web import create_service_app
from services.sim.lsl_markers import MarkerPublisher
from services.sim.registry import SessionRegistry
from services.sim.routes import images, oracle, paced, service, sessions, stream
from services.sim.settings import SimSettings


def create_app(settings: SimSettings | None = None) -> FastAPI:
    """Build the sim service; ``settings`` default to the environment's ``BGRL_SIM_*``."""
    settings = settings if settings is not None else load_settings(SimSettings)
    configure_logging(settings.log_level, json_lines=settings.log_json)
    configure_log_file(settings, "sim")

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        publisher = None
        if settings.lsl_markers:
            try:
                publisher = MarkerPublisher(
                    settings.marker_source_id or f"bgrl-sim@{socket.gethostname()}:{settings.port}"
                )
            except Exception as exc:
                raise RuntimeError(
                    "cannot open the LSL marker outlet (liblsl failed: "
                    f"{type(exc).__name__}: {exc}); set BGRL_SIM_LSL_MARKERS=false to run "
                    "without markers"
                ) from exc
        app.state.publisher = publisher
        app.state.registry = SessionRegistry(
            max_sessions=settings.max_sessions,
            idle_timeout_s=settings.session_idle_timeout_s,
            publisher=publisher,
            extra_map_dirs=tuple(settings.extra_map_dirs),
            frame_size=(settings.frame_width, settings.frame_height),
            max_queued_actions=settings.max_queued_actions,
            oracle_cache_dir=settings.oracle_cache_dir,
        )
        try:
            yield
        finally:
            app.state.registry.close_all()
            if publisher is not None:
                publisher.close()

    app = create_service_app(
        name="sim",
        title="BrainNav sim service",
        summary="Navigation sim sessions, oracle, frame stream and LSL action markers.",
        version="0.1.0",
        max_body_size=settings.max_upload_bytes,
        lifespan=lifespan,
        routers=[m.router for m in (service, sessions, oracle, images, paced, stream)],
        health=service.health_fields,
        service_token=settings.service_token,
    )
    app.state.settings = settings
    return app


app = create_app()
