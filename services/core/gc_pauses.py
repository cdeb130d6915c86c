"""Short garbage-collector pauses in long-running services: freeze what start-up built.

CPython's full (generation 2) collection walks every object the collector tracks. A service
that has imported torch, MNE or SQLAlchemy holds 120 000 to 260 000 of them, and one full
collection then takes 65 to 180 ms on this project's 2-core machines (docs/benchmarks.md,
"Garbage-collector pauses"): a pause that lands on whichever request or closed-loop step is
in flight. What start-up builds (modules, classes, routes, models) lives as long as the
process, so :func:`freeze_startup_objects` moves it out of the collector's reach
(``gc.freeze``, as the CPython documentation advises for long-lived servers); later
collections walk only what was created since. :func:`unfreeze` gives it back at shutdown,
so a process that starts and stops several services (as the tests do) keeps no garbage.
"""

from __future__ import annotations

import gc
from collections.abc import AsyncIterator, Callable
from contextlib import AbstractAsyncContextManager, asynccontextmanager, nullcontext
from typing import Any


def freeze_startup_objects() -> None:
    """Collect once, then exempt every object alive now from later collections."""
    gc.collect()
    gc.freeze()


def unfreeze() -> None:
    """Return the frozen objects to the collector (their garbage is collected again)."""
    gc.unfreeze()


def frozen_after_startup(
    lifespan: Callable[[Any], AbstractAsyncContextManager[None]] | None,
) -> Callable[[Any], AbstractAsyncContextManager[None]]:
    """``lifespan`` (an ASGI app's, or none) that freezes the start-up objects once it has
    started and unfreezes them when it stops."""

    @asynccontextmanager
    async def run(app: Any) -> AsyncIterator[None]:
        async with lifespan(app) if lifespan is not None else nullcontext():
            freeze_startup_objects()
            try:
                yield
            finally:
                unfreeze()

    return run
