"""The EEG service: recordings, calibration jobs, classifiers, live decoding.

Run with ``uvicorn services.eeg.service.app:app --port 8002`` (or ``bgrl serve``); configuration
comes from ``BGRL_EEG_*`` (:class:`~services.eeg.service.settings.EEGSettings`). Endpoints are
documented in ``docs/eeg.md`` (section "EEG service") and at ``/docs``.

Layout (the pattern of every service): ``settings`` (configuration), ``schemas`` (request
and response bodies), ``errors`` (what a request can be refused with), ``store``, ``jobs``,
``live_session`` and ``state`` (what the service keeps and runs), ``deps`` (FastAPI
dependencies), ``routes/`` (one module per resource) and this factory.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from services.core.logging import configure_log_file, configure_logging
from services.core.settings import load_settings
from services.core.web import create_service_app
from services.eeg.service.routes import classifiers, jobs, live, recordings
from services.eeg.service.settings import EEGSettings
from services.eeg.service.state import EEGService


def create_app(settings: EEGSettings | None = None) -> FastAPI:
    """Build the EEG service; ``settings`` default to the environment's ``BGRL_EEG_*``."""
    settings = settings if settings is not None else load_settings(EEGSettings)
    configure_logging(settings.log_level, json_lines=settings.log_json)
    configure_log_file(settings, "eeg")

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        import torch

        # One intra-op thread: an EEGNet pass on one live epoch takes ~1 ms on one thread,
        # while two OpenMP threads on a busy 2-core machine spin for tens of ms (p99 > 100 ms).
        torch.set_num_threads(1)
        service = EEGService(settings, asyncio.get_running_loop())
        app.state.service = service
        try:
            yield
        finally:
            await asyncio.to_thread(service.close)

    app = create_service_app(
        name="eeg",
        title="BrainNav EEG service",
        summary="Recordings, ErrP calibration, classifiers and live decoding.",
        version="0.2.0",
        max_body_size=settings.max_upload_bytes,
        lifespan=lifespan,
        routers=[recordings.router, jobs.router, classifiers.router, live.router],
        service_token=settings.service_token,
    )
    app.state.settings = settings
    return app


app = create_app()
