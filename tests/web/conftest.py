"""Browser tests of the dashboard: the real api (uvicorn, SQLite in a temp folder) on loopback,
a real ``bgrl worker`` when a test needs job progress (the live pages' tests add the sim, EEG
and learner services: ``run_services``), and Debian's Chromium driven headless by Playwright
(never a downloaded browser). Skipped with the reason where /usr/bin/chromium or
Playwright is absent.

Screenshots go to a temp folder (printed at the end); set ``BGRL_WEB_SCREENSHOTS`` to a folder
(e.g. ``docs/screenshots``) to write them there instead.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import pytest

from benchmarks.browser import CHROMIUM, CHROMIUM_ARGS
from tests.helpers import (
    env_without_bgrl,
    fast_password_hashing,
    free_port,
    serve_in_thread,
    start_service,
    stop_processes,
    wait_healthy,
)

ADMIN = ("admin@lab.test", "admin-password-123")
STAFF = ("staff@lab.test", "staff-password-123")
VIEWER = ("viewer@lab.test", "viewer-password-123")
ACCOUNTS = {"admin": ADMIN, "staff": STAFF, "viewer": VIEWER}
REPO = Path(__file__).resolve().parents[2]

try:
    from playwright.sync_api import Browser, BrowserContext, Page, sync_playwright
except ImportError:  # pragma: no cover - dev dependency missing
    sync_playwright = None


def _skip_reason() -> str | None:
    if sync_playwright is None:
        return "playwright (Python) is not installed: pip install -e '.[dev]'"
    if not CHROMIUM.exists():
        return "no /usr/bin/chromium: apt-get install -y chromium (.ci/run does)"
    return None


@dataclass
class Server:
    """The api process, its environment and a token per role (for set-up through the API)."""

    base_url: str
    root: Path
    env: dict[str, str]
    tokens: dict[str, str] = field(default_factory=dict)
    worker: subprocess.Popen[bytes] | None = None
    sim_url: str | None = None
    database_url: str | None = None

    def call(self, method: str, path: str, role: str = "admin", **kwargs: Any) -> Any:
        response = httpx.request(
            method,
            self.base_url + path,
            headers={"Authorization": f"Bearer {self.tokens[role]}"},
            timeout=30,
            **kwargs,
        )
        assert response.status_code < 300, response.text
        return response.json() if response.content else None

    def start_worker(self) -> None:
        """One ``bgrl worker`` on the api's database and broker (it builds the map's oracle
        lattice at its first job, as on a fresh host)."""
        log = self.root / "worker.log"
        self.worker = subprocess.Popen(
            [sys.executable, "-m", "services.cli.main", "worker", "--name", "web"],
            cwd=self.root,
            env=self.env,
            stdout=log.open("wb"),
            stderr=subprocess.STDOUT,
        )


@contextmanager
def run_services(
    root: Path, env: dict[str, str], names: tuple[str, ...]
) -> Iterator[dict[str, str]]:
    """The named services (sim, eeg, learner) as uvicorn processes on free loopback ports,
    logging to ``root/<name>.log``; their base URLs once all answer ``/health``."""
    ports = {name: free_port() for name in names}
    urls = {name: f"http://127.0.0.1:{port}" for name, port in ports.items()}
    procs: dict[str, subprocess.Popen[bytes]] = {}
    try:
        for name in names:
            procs[name] = start_service(
                name, ports[name], env=env, cwd=root, log=root / f"{name}.log"
            )
        for name in names:
            wait_healthy(urls[name], procs[name], root / f"{name}.log")
        yield urls
    finally:
        stop_processes(procs.values())


def _login(base_url: str, email: str, password: str) -> str:
    response = httpx.post(
        base_url + "/api/v1/auth/token", data={"username": email, "password": password}
    )
    assert response.status_code == 200, response.text
    return response.json()["access_token"]


@contextmanager
def serve_api(settings: Any) -> Iterator[str]:
    """The api (uvicorn in a thread) on a free loopback port; its base URL. Password hashing
    at minimal cost (the tests check pages, not hashes)."""
    from services.api.app import create_app

    patch = pytest.MonkeyPatch()
    fast_password_hashing(patch)
    try:
        with serve_in_thread(create_app(settings)) as base_url:
            yield base_url
    finally:
        patch.undo()


def add_accounts(srv: Server, roles: tuple[str, ...] = ("staff", "viewer")) -> None:
    """Sign in as the admin and create (and sign in) an account per role."""
    srv.tokens["admin"] = _login(srv.base_url, *ADMIN)
    for role in roles:
        email, password = ACCOUNTS[role]
        srv.call("POST", "/api/v1/users", json={"email": email, "password": password, "role": role})
        srv.tokens[role] = _login(srv.base_url, email, password)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """The api on a temporary SQLite database with an admin, a staff and a viewer account,
    and a real ``bgrl worker``."""
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    from services.api.settings import ApiSettings

    root = tmp_path_factory.mktemp("web")
    env = {
        **env_without_bgrl(),
        "BGRL_DATA_DIR": str(root / "data"),
        "BGRL_JOB_HEARTBEAT_S": "0.5",
        "BGRL_LOG_LEVEL": "INFO",
    }
    settings = ApiSettings(
        data_dir=root / "data",
        admin_email=ADMIN[0],
        admin_password=ADMIN[1],
        eeg_url=None,
        job_heartbeat_s=0.5,
    )
    with serve_api(settings) as base_url:
        srv = Server(base_url, root, env)
        srv.start_worker()  # starts up while the first tests run
        try:
            add_accounts(srv)
            yield srv
        finally:
            if srv.worker is not None:
                stop_processes([srv.worker])


@pytest.fixture(scope="module")
def browser() -> Iterator[Browser]:
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(
            executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS
        )
        try:
            yield chromium
        finally:
            chromium.close()


@pytest.fixture(scope="session")
def screenshot_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Where screenshots are saved (a temp folder unless BGRL_WEB_SCREENSHOTS is set)."""
    configured = os.environ.get("BGRL_WEB_SCREENSHOTS")
    folder = Path(configured) if configured else tmp_path_factory.mktemp("web-screenshots")
    folder.mkdir(parents=True, exist_ok=True)
    return folder


class Watch:
    """What a page did that it should not: console errors and requests off this host."""

    def __init__(self, origin: str) -> None:
        self.host = urlsplit(origin).netloc
        self.console_errors: list[str] = []
        self.outside: list[str] = []

    def route(self, route: Any) -> None:
        url = route.request.url
        parts = urlsplit(url)
        local = parts.scheme in ("blob", "data") or (
            parts.netloc == self.host and parts.hostname == "127.0.0.1"
        )
        if local:
            route.continue_()
        else:
            self.outside.append(url)
            route.abort()

    def errors_except(self, *allowed: str) -> list[str]:
        return [e for e in self.console_errors if not any(re.search(a, e) for a in allowed)]


@pytest.fixture
def context(
    browser: Browser, server: Server, request: pytest.FixtureRequest
) -> Iterator[tuple[BrowserContext, Watch]]:
    """A fresh browser profile at 1280x800; every request off 127.0.0.1 is blocked and
    recorded, every console error collected; both must stay empty (checked afterwards)."""
    scheme = getattr(request, "param", "light")
    ctx = browser.new_context(
        base_url=server.base_url,
        viewport={"width": 1280, "height": 800},
        color_scheme=scheme,
        accept_downloads=True,
    )
    watch = Watch(server.base_url)
    ctx.route("**/*", watch.route)
    ctx.on("weberror", lambda error: watch.console_errors.append(f"pageerror: {error.error}"))

    def on_page(page: Page) -> None:
        page.on(
            "console",
            lambda msg: watch.console_errors.append(msg.text) if msg.type == "error" else None,
        )

    ctx.on("page", on_page)
    ctx.set_default_timeout(15_000)
    try:
        yield ctx, watch
    finally:
        ctx.close()
    assert watch.outside == [], f"requests left 127.0.0.1: {watch.outside}"


def open_as(ctx: BrowserContext, server: Server, role: str, path: str) -> Page:
    """A page at ``path`` already signed in as ``role`` (the token the form would store)."""
    token = server.tokens[role]
    ctx.add_init_script(
        script=f"if (location.origin === '{server.base_url}') "
        f"sessionStorage.setItem('bgrl.access_token', '{token}');"
    )
    page = ctx.new_page()
    page.goto(path)
    page.wait_for_selector("#account button")
    return page
