"""The services freeze their start-up objects out of full collections while they run."""

from __future__ import annotations

import asyncio
import gc
import weakref
from contextlib import asynccontextmanager

from fastapi.testclient import TestClient

from services.core.gc_pauses import frozen_after_startup
from services.core.web import create_service_app


def test_a_service_freezes_its_startup_objects_while_it_runs_and_unfreezes_them_after():
    started: list[int] = []

    @asynccontextmanager
    async def lifespan(_app):
        started.append(gc.get_freeze_count())  # the service's own start-up comes first
        yield

    app = create_service_app(
        name="probe", title="probe", summary="", version="0", max_body_size=1024,
        lifespan=lifespan,
    )  # fmt: skip
    gc.unfreeze()
    with TestClient(app) as client:
        assert started == [0]
        assert gc.get_freeze_count() > 1000  # the imported modules, classes, routes
        assert client.get("/health").json()["status"] == "ok"
    assert gc.get_freeze_count() == 0


class _Cycle:
    def __init__(self) -> None:
        self.me = self  # only the collector frees it


def test_garbage_of_frozen_objects_is_collected_again_after_shutdown():
    holder = [_Cycle()]  # alive at start-up, so frozen with the rest
    ref = weakref.ref(holder[0])

    async def run() -> None:
        async with frozen_after_startup(None)(object()):
            holder.clear()  # garbage now, but frozen: out of the collector's reach
            gc.collect()
            assert ref() is not None

    asyncio.run(run())
    gc.collect()
    assert ref() is None
