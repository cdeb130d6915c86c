"""The learner service: online HF-training sessions (Fhat, its buffer and pi_HF) over HTTP.

Run with ``uvicorn services.learner.service.app:app --port 8003`` (or ``bgrl up``);
configuration comes from ``BGRL_LEARNER_*`` (:class:`LearnerSettings`), the artifact store
from the platform's ``BGRL_ARTIFACT_DIR``. Endpoints are documented in
``docs/learner-service.md`` and at ``/docs``.

Layout (the pattern of every service): ``settings``, ``schemas``, ``errors``, ``session``
(one session's learning), ``store`` (the sessions and their checkpoints), ``journal`` (every
change since a checkpoint), ``export`` (TorchScript), ``deps``, ``routes/`` (one module per
resource) and this factory.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import torch
from fastapi import FastAPI, Request

from services.core.artifacts import ArtifactStore
from services.core.logging import configure_log_file, configure_logging
from services.core.platform import PlatformSettings
from services.core.settings import load_settings
from services.core.web import create_service_app
from services.learner.service.routes import hf_sessions, labels, policy
from services.learner.service.settings import LearnerSettings
from services.learner.service.store import SessionStore


def _health(request: Request) -> dict[str, Any]:
    store: SessionStore | None = getattr(request.app.state, "store", None)
    return {"sessions": len(store.list()) if store is not None else 0}


def create_app(
    settings: LearnerSettings | None = None, platform: PlatformSettings | None = None
) -> FastAPI:
    """Build the learner service; settings default to the environment's."""
    settings = settings if settings is not None else load_settings(LearnerSettings)
    platform = platform if platform is not None else load_settings(PlatformSettings)
    configure_logging(settings.log_level, json_lines=settings.log_json)
    configure_log_file(settings, "learner")

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        torch.set_num_threads(1)  # a 16-unit network: threads only add contention
        store = SessionStore(settings, ArtifactStore(platform.resolved_artifact_dir))
        store.load_all()
        app.state.store = store
        yield
        store.close()

    app = create_service_app(
        name="learner",
        title="BrainNav learner service",
        summary="Online human-feedback training: Fhat, its replay buffer and pi_HF.",
        version="0.1.0",
        max_body_size=settings.max_upload_bytes,
        lifespan=lifespan,
        routers=[hf_sessions.router, policy.router, labels.router],
        health=_health,
        service_token=settings.service_token,
    )
    app.state.settings = settings
    return app


app = create_app()
