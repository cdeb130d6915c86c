"""CPU per request of the api, in process: what a route costs whatever the machine's load.

``python -m benchmarks.api_cpu`` prints the figures on a fresh database (SQLite, and
PostgreSQL when reachable); ``bgrl bench api`` reports them too. The app is called straight
through ASGI (no HTTP parsing, no socket, no test client), one request at a time, on the
event loop uvicorn would use; the figure is the process's CPU time (``time.process_time``,
every thread) divided by the requests, the median of a few repeats. The job list's peer is
the bare app answering the same bytes (:mod:`benchmarks.api_bare`), measured alike in the
same run. On a shared machine
this is the robust figure: wall-clock latency under load also measures everyone else's work.
"""

from __future__ import annotations

import asyncio
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any
from urllib.parse import urlencode

from fastapi import FastAPI
from pydantic import SecretStr

from benchmarks.api_bare import create_bare_app
from benchmarks.api_data import ADMIN_EMAIL, PG_SKIP_REASON, postgres_schema, store_jobs
from benchmarks.api_load import BARE, JOBS_ROUTE, LIST
from services.api.app import create_app
from services.api.settings import ApiSettings
from services.core.db.migrate import upgrade_database

ASGI_ADDRESS = ("127.0.0.1", 8000)


async def asgi_get(
    app: FastAPI, path: str, headers: dict[str, str], body: bytes = b"", method: str = "GET"
) -> tuple[int, bytes]:
    """One request through the ASGI app: (status, body)."""
    route, _, query = path.partition("?")
    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": method,
        "scheme": "http",
        "path": route,
        "raw_path": route.encode(),
        "query_string": query.encode(),
        "root_path": "",
        "headers": [(k.lower().encode(), v.encode()) for k, v in headers.items()],
        "client": ("127.0.0.1", 50000),
        "server": ASGI_ADDRESS,
    }
    delivered = False

    async def receive() -> dict[str, Any]:
        nonlocal delivered
        if not delivered:
            delivered = True
            return {"type": "http.request", "body": body, "more_body": False}
        await asyncio.Event().wait()  # the client never disconnects
        raise AssertionError("unreachable")

    status, chunks = 0, []

    async def send(message: dict[str, Any]) -> None:
        nonlocal status
        if message["type"] == "http.response.start":
            status = message["status"]
        elif message["type"] == "http.response.body":
            chunks.append(message.get("body", b""))

    await app(scope, receive, send)
    return status, b"".join(chunks)


async def _measure(
    app: FastAPI, path: str, headers: dict[str, str], requests: int, repeats: int
) -> float:
    """CPU ms per ``GET path`` of ``app``: the median of ``repeats`` runs of ``requests``."""
    for _ in range(20):  # warm caches (compiled queries, pydantic, the pool)
        status, body = await asgi_get(app, path, headers)
        if status != 200:
            raise RuntimeError(f"GET {path}: {status} {body[:300]!r}")
    per_request = []
    for _ in range(repeats):
        started = time.process_time()
        for _ in range(requests):
            await asgi_get(app, path, headers)
        per_request.append(1000 * (time.process_time() - started) / requests)
    return statistics.median(per_request)


async def _profile(
    app: FastAPI, path: str, headers: dict[str, str], requests: int, out: Path
) -> float:
    """cProfile ``requests`` requests of ``path`` into ``out`` (pstats; CPU time, so that
    other processes' work on a loaded machine does not count), with calls to the thread
    pool run inline so that the profiler sees them; the CPU ms per request."""
    import cProfile
    from unittest import mock

    async def inline(func: Any, *args: Any, **kwargs: Any) -> Any:
        return func(*args, **kwargs)

    patches = [
        mock.patch(f"{module}.run_in_threadpool", inline)
        for module in ("fastapi.dependencies.utils", "fastapi.routing", "fastapi.concurrency")
    ]
    patches += [
        mock.patch(f"{name}.run_in_threadpool", inline)
        for name, module in list(sys.modules.items())
        if name.startswith("services.api") and hasattr(module, "run_in_threadpool")
    ]
    for patch in patches:
        patch.start()
    try:
        for _ in range(20):
            await asgi_get(app, path, headers)
        profiler = cProfile.Profile(time.process_time)
        started = time.process_time()
        profiler.enable()
        for _ in range(requests):
            await asgi_get(app, path, headers)
        profiler.disable()
        elapsed = time.process_time() - started
    finally:
        for patch in patches:
            patch.stop()
    profiler.dump_stats(out)
    return 1000 * elapsed / requests


def cpu_ms_per_request(
    database_url: str,
    data_dir: Path,
    admin_email: str,
    admin_password: str,
    path: str = JOBS_ROUTE,
    *,
    requests: int = 200,
    repeats: int = 5,
    profile_to: Path | None = None,
) -> dict[str, float]:
    """CPU ms per ``GET path`` of the api (signed in as the admin, with an API token) on an
    already filled database (``list``) and of the bare app answering the same bytes
    (``bare``), each the median over ``repeats`` runs of ``requests`` requests, and their
    ratio (``list_to_bare``). With ``profile_to``, the api's route is profiled instead (see
    :func:`_profile`): ``{"list": ms}``."""
    upgrade_database(database_url)
    settings = ApiSettings(
        data_dir=data_dir,
        database_url=database_url,
        admin_email=admin_email,
        admin_password=SecretStr(admin_password),
        eeg_url="",
        log_level="WARNING",
        migrate_on_start=False,
    )
    app = create_app(settings)

    async def run() -> dict[str, float]:
        async with app.router.lifespan_context(app):
            form = urlencode({"username": admin_email, "password": admin_password}).encode()
            status, body = await asgi_get(
                app,
                "/api/v1/auth/token",
                {"content-type": "application/x-www-form-urlencoded"},
                form,
                method="POST",
            )
            if status != 200:
                raise RuntimeError(f"sign-in failed: {status} {body[:300]!r}")
            auth = {"authorization": f"Bearer {json.loads(body)['access_token']}"}
            # the load of ``bgrl bench api`` signs in with an API token: so does this
            status, body = await asgi_get(
                app,
                "/api/v1/tokens",
                {**auth, "content-type": "application/json"},
                json.dumps({"name": "api-cpu", "expires_in_days": 1}).encode(),
                method="POST",
            )
            if status != 201:
                raise RuntimeError(f"API token not created: {status} {body[:300]!r}")
            auth = {"authorization": f"Bearer {json.loads(body)['token']}"}
            if profile_to is not None:
                return {LIST: await _profile(app, path, auth, requests, profile_to)}
            listed = await _measure(app, path, auth, requests, repeats)
            status, body = await asgi_get(app, path, auth)
            bare = await _measure(create_bare_app(body), path, auth, requests, repeats)
            return {LIST: listed, BARE: bare, "list_to_bare": listed / bare}

    return asyncio.run(run())


def main(argv: list[str] | None = None) -> None:
    """``python -m benchmarks.api_cpu``: CPU ms per request of the job list and of its bare
    peer, as ``bgrl bench api`` measures them, on a fresh SQLite database and, when
    reachable, PostgreSQL (JSON on stdout)."""
    import argparse
    import tempfile

    parser = argparse.ArgumentParser(prog="python -m benchmarks.api_cpu")
    parser.add_argument("--jobs-stored", type=int, default=1000)
    parser.add_argument("--requests", type=int, default=200)
    parser.add_argument(
        "--profile",
        type=Path,
        metavar="DIR",
        help="cProfile the list route instead: DIR/<database>.pstats (thread-pool calls inline)",
    )
    parser.add_argument("--databases", default="sqlite,postgresql", help="comma-separated")
    args = parser.parse_args(argv)
    if args.profile is not None:
        args.profile.mkdir(parents=True, exist_ok=True)
    password = "bench-password-123"
    figures: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="bgrl-api-cpu-") as tmp, postgres_schema() as pg_url:
        urls = {"sqlite": f"sqlite:///{Path(tmp) / 'bgrl.db'}", "postgresql": pg_url}
        for name, url in urls.items():
            if name not in args.databases.split(","):
                continue
            if url is None:
                figures[name] = {"skipped": PG_SKIP_REASON}
                continue
            upgrade_database(url)
            store_jobs(url, args.jobs_stored)
            data_dir = Path(tmp) / name
            figures[name] = cpu_ms_per_request(
                url, data_dir, ADMIN_EMAIL, password, JOBS_ROUTE,
                requests=args.requests,
                profile_to=None if args.profile is None else args.profile / f"{name}.pstats",
            )  # fmt: skip
    json.dump({"jobs_stored": args.jobs_stored, "cpu_ms_per_request": figures}, sys.stdout)
    print()


if __name__ == "__main__":
    main()
