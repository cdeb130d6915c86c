"""Helpers shared by the tests that run the platform for real on loopback: free ports, an
ASGI app served by uvicorn in a thread, the services as uvicorn processes, waiting for their
``/health`` and stopping processes. Imported as ``tests.helpers`` (the repository root is on
``sys.path`` under ``python -m pytest``, as for ``tests.<package>.conftest``)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest

from services.cli.serve import SERVICES

ASGI_APPS = {spec.name: spec.asgi_app for spec in SERVICES}
"""Every HTTP service's ASGI app (api, sim, eeg, learner), as ``bgrl up`` starts it with
uvicorn."""
INTERNAL_SERVICES = ("sim", "eeg", "learner")
"""The services behind the api (loopback only, the internal token)."""


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now (the OS picks it)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def env_without_bgrl() -> dict[str, str]:
    """This process's environment without ``BGRL_*`` settings: a child process gets only
    the settings the test gives it."""
    return {k: v for k, v in os.environ.items() if not k.startswith("BGRL_")}


def fast_password_hashing(monkeypatch: pytest.MonkeyPatch) -> None:
    """Argon2 at minimal cost: the tests check the flow, not the hash's strength."""
    from argon2 import PasswordHasher

    from services.api import security

    monkeypatch.setattr(
        security, "_hasher", PasswordHasher(time_cost=1, memory_cost=64, parallelism=1)
    )


@contextmanager
def serve_in_thread(app: Any, start_timeout_s: float = 60.0) -> Iterator[str]:
    """Serve the ASGI ``app`` with uvicorn in a thread on 127.0.0.1 (a free port, bound here
    so no other process can take it first); yields its base URL, stops it on exit."""
    import uvicorn

    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + start_timeout_s
        while not server.started:
            if not thread.is_alive() or time.monotonic() > deadline:
                pytest.fail("the app served in a thread did not start (see the log above)")
            time.sleep(0.02)
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=15)
        sock.close()


def start_service(
    name: str, port: int, *, env: dict[str, str], cwd: Path, log: Path
) -> subprocess.Popen[bytes]:
    """The service ``name`` (a key of ``ASGI_APPS``) as a uvicorn process on
    127.0.0.1:``port`` with exactly ``env``; its output appended to ``log``."""
    return subprocess.Popen(
        [sys.executable, "-m", "uvicorn", ASGI_APPS[name], "--host", "127.0.0.1",
         "--port", str(port)],
        env=env, cwd=cwd, stdout=log.open("ab"), stderr=subprocess.STDOUT,
    )  # fmt: skip


def wait_healthy(
    url: str,
    proc: subprocess.Popen[bytes],
    log: Path,
    timeout_s: float = 120.0,
    path: str = "/health",
) -> None:
    """Poll ``url`` + ``path`` until it answers 2xx; fail with the end of ``log`` if ``proc``
    (the process serving it) exits or ``timeout_s`` passes (torch and mne imports take long
    on a loaded machine)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            if httpx.get(url + path, timeout=2).is_success:
                return
        except httpx.HTTPError:
            pass
        if proc.poll() is not None or time.monotonic() > deadline:
            state = "exited" if proc.poll() is not None else f"is not healthy after {timeout_s} s"
            tail = log.read_text(errors="replace")[-3000:] if log.exists() else "(no log)"
            pytest.fail(f"{url} {state}:\n{tail}")
        time.sleep(0.2)


def stop_processes(procs: Iterable[subprocess.Popen[bytes]], timeout_s: float = 15.0) -> None:
    """SIGTERM every process still running, then wait for each; kill one that has not
    stopped ``timeout_s`` after its turn came."""
    procs = list(procs)
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
    for proc in procs:
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
