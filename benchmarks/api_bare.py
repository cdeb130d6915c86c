"""The peer of ``bgrl bench api``'s job list: a bare FastAPI app whose one route,
``GET /api/v1/jobs``, answers the bytes the platform's list gave (read once from a file), with
no middleware, no sign-in, no database and no validation. Run in the same way as the api
(``uvicorn --factory benchmarks.api_bare:app_from_env``, ``BGRL_BENCH_BARE_BODY`` naming the
file), it is what the framework and the server cost for the same answer; the list's latency
and CPU are compared with it in the same run."""

from __future__ import annotations

import os
from pathlib import Path

from fastapi import FastAPI, Response

BODY_ENV = "BGRL_BENCH_BARE_BODY"
"""The environment variable naming the file of the answer's bytes (JSON)."""
JOBS_PATH = "/api/v1/jobs"


def create_bare_app(body: bytes) -> FastAPI:
    """A FastAPI app answering ``GET /api/v1/jobs`` (any query) with ``body`` as JSON."""
    app = FastAPI(openapi_url=None, docs_url=None, redoc_url=None)

    @app.get(JOBS_PATH)
    async def jobs() -> Response:
        return Response(body, media_type="application/json")

    return app


def app_from_env() -> FastAPI:
    """:func:`create_bare_app` of the file ``BGRL_BENCH_BARE_BODY`` names (uvicorn's factory)."""
    return create_bare_app(Path(os.environ[BODY_ENV]).read_bytes())
