"""The platform api: users, lab resources, recordings and jobs under ``/api/v1``.

Run with ``uvicorn services.api.app:app --port 8000`` (``bgrl up`` starts it with the rest);
configuration comes from ``BGRL_*`` environment variables (:class:`ApiSettings`). Endpoints
are documented in ``docs/api.md`` and at ``/docs``.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import APIRouter, FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse
from sqlalchemy.exc import OperationalError

from services.api.accounts import ensure_first_admin
from services.api.errors import TooManyRequestsError, UnauthorizedError
from services.api.metrics import PlatformCollector, admin_or_internal
from services.api.ratelimit import LoginLimiter
from services.api.routes import (
    artifacts,
    audit,
    auth,
    classifiers,
    dashboard,
    health,
    hf_models,
    job_events,
    job_kinds,
    jobs,
    live_sessions,
    recordings,
    relay,
    rigs,
    sessions,
    subjects,
    tokens,
    users,
)
from services.api.security import dummy_hash, load_jwt_key
from services.api.settings import ApiSettings
from services.core.artifacts import ArtifactStore
from services.core.db.migrate import upgrade_database
from services.core.db.session import make_engine, make_session_factory, pool_capacity
from services.core.logging import configure_log_file, configure_logging
from services.core.queue import make_celery
from services.core.settings import load_settings
from services.core.web import create_service_app

log = logging.getLogger(__name__)

DATABASE_RETRY_AFTER_S = 2
"""What a request that found the database unreachable asks its client to wait (503)."""

MULTIPART_OVERHEAD_BYTES = 64 * 1024
"""Room for a multipart envelope around an upload of ``max_upload_bytes``."""

ROUTERS = (
    jobs.router,
    health.router,
    auth.router,
    users.router,
    tokens.router,
    rigs.router,
    subjects.router,
    sessions.router,
    live_sessions.router,
    recordings.router,
    classifiers.router,
    hf_models.router,
    job_kinds.router,
    job_events.router,
    relay.router,
    artifacts.router,
    audit.router,
    dashboard.router,
)
"""The api's routers, in the order requests are matched against their routes: the jobs
first, as the job list is the route read most (scripts and the dashboard poll it). No two
routes share a method and path (``tests/api/test_job_page.py``), so the order changes what a
request costs, never which route answers it."""


def create_app(settings: ApiSettings | None = None) -> FastAPI:
    """Build the api; ``settings`` default to the environment's ``BGRL_*`` variables."""
    settings = settings if settings is not None else load_settings(ApiSettings)
    configure_logging(settings.log_level, json_lines=settings.log_json)
    configure_log_file(settings, "api")

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        settings.ensure_data_dir()
        url = settings.resolved_database_url
        if settings.migrate_on_start:
            await run_in_threadpool(upgrade_database, url)
        engine = make_engine(url, connections=settings.database_connections)
        app.state.engine = engine
        app.state.sessions = make_session_factory(engine)
        app.state.db_slots = asyncio.Semaphore(pool_capacity(engine))
        app.state.store = ArtifactStore(settings.resolved_artifact_dir)
        await run_in_threadpool(app.state.store.remove_abandoned_parts)  # of a killed api
        app.state.celery = make_celery(settings)
        app.state.jwt_key = load_jwt_key(settings)
        await run_in_threadpool(dummy_hash)  # not on the first unknown e-mail's login
        await run_in_threadpool(ensure_first_admin, app.state.sessions, settings)
        try:
            yield
        finally:
            engine.dispose()

    # uploads may be as large as max_upload_bytes; every other body max_request_bytes
    uploads = APIRouter(max_body_size=settings.max_upload_bytes + MULTIPART_OVERHEAD_BYTES)
    uploads.include_router(recordings.router)
    after_uploads = ROUTERS[ROUTERS.index(recordings.router) + 1 :]
    app = create_service_app(
        name="api",
        title="Brain-guided RL platform API",
        summary="Subjects, sessions, recordings, guided-PPO jobs and their models.",
        version="0.1.0",
        max_body_size=settings.max_request_bytes,
        lifespan=lifespan,
        routers=[*ROUTERS[: ROUTERS.index(recordings.router)], uploads, *after_uploads],
        metrics_guard=admin_or_internal(settings.service_token),
    )
    app.state.metrics.register(PlatformCollector(app))
    app.state.settings = settings
    app.state.limiter = LoginLimiter(settings.login_max_failures, settings.login_window_s)

    @app.exception_handler(UnauthorizedError)
    async def unauthorized(request: Request, exc: UnauthorizedError) -> JSONResponse:
        return JSONResponse(
            status_code=401,
            content={"detail": str(exc), "field": exc.field},
            headers={"WWW-Authenticate": "Bearer"},
        )

    @app.exception_handler(TooManyRequestsError)
    async def too_many(request: Request, exc: TooManyRequestsError) -> JSONResponse:
        return JSONResponse(
            status_code=429,
            content={"detail": str(exc), "field": exc.field},
            headers={"Retry-After": str(exc.retry_after_s)},
        )

    @app.exception_handler(OperationalError)
    async def database_unreachable(request: Request, exc: OperationalError) -> JSONResponse:
        """The database restarting or cut off: 503 with Retry-After, not a 500. The
        request's transaction was rolled back; the pool drops the dead connection, so a
        request sent again gets a new one once the database is back."""
        log.warning("%s %s: the database cannot be reached: %s",
                    request.method, request.url.path, exc.orig or exc)  # fmt: skip
        return JSONResponse(
            status_code=503,
            content={
                "detail": "the database cannot be reached (restarting?); "
                f"try again in {DATABASE_RETRY_AFTER_S} s",
                "field": None,
            },
            headers={"Retry-After": str(DATABASE_RETRY_AFTER_S)},
        )

    return app


app = create_app()
