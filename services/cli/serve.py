"""``bgrl up`` (alias ``bgrl serve``): the whole platform on one machine, one command.

Creates the data folder, brings the database to the current schema, then starts the api
(8000; ``BGRL_API_WORKERS`` processes behind that port), sim (8001), EEG (8002) and learner
(8003) services as uvicorn processes and ``BGRL_WORKERS`` job workers. Every value comes
from the services' settings (``BGRL_PORT``, ``BGRL_SIM_HOST``, ``BGRL_EEG_PORT``...),
validated before anything starts: a bad one is one line naming the variable. A worker that
dies is restarted; if an HTTP service dies, everything stops. Ctrl-C or SIGTERM stops every
process within 10 s (workers hand their running job back to the queue); the data folder
keeps the database, broker and artifacts for the next start.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib
import importlib.util
import logging
import os
import secrets
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import typer

from services.core.settings import BaseServiceSettings, SettingsError, load_settings

logger = logging.getLogger("bgrl.up")

STOP_TIMEOUT_S = 7.0
"""Seconds a child gets to stop after SIGTERM before it is killed (all stop within 10 s)."""
WORKER_RESTART_DELAY_S = 2.0
"""A worker that died is restarted after this pause (no busy loop if it dies at start)."""


@dataclass(frozen=True)
class ServiceSpec:
    """One HTTP service of the platform."""

    name: str
    asgi_app: str
    settings_class: str
    """``module:Class`` of the service's settings (its host, port and the rest)."""

    @property
    def module(self) -> str:
        return self.asgi_app.split(":", 1)[0]

    def available(self) -> bool:
        """True when the service's module and its packages are in this installation (an
        install of the ``api`` extra has no sim: its package needs gymnasium)."""
        try:
            return importlib.util.find_spec(self.module) is not None
        except ModuleNotFoundError:
            return False

    def load_settings(self) -> BaseServiceSettings:
        """The service's settings from the environment (SettingsError: one line)."""
        module, _, name = self.settings_class.partition(":")
        cls = getattr(importlib.import_module(module), name)
        return load_settings(cls)


SERVICES = (
    ServiceSpec("api", "services.api.app:app", "services.api.settings:ApiSettings"),
    ServiceSpec("sim", "services.sim.app:app", "services.sim.settings:SimSettings"),
    ServiceSpec("eeg", "services.eeg.app:app", "services.eeg.settings:EEGSettings"),
    ServiceSpec(
        "learner",
        "services.learner.service.app:app",
        "services.learner.service.settings:LearnerSettings",
    ),
)


def _die_with_parent() -> None:  # pragma: no cover - runs in the child before exec
    """Linux: the child gets SIGTERM if ``bgrl up`` itself is killed (nothing orphaned)."""
    with contextlib.suppress(OSError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class Child:
    """A child process of ``bgrl up`` (in its own process group, so only we signal it)."""

    def __init__(self, name: str, cmd: list[str], env: dict[str, str] | None = None) -> None:
        self.name = name
        self.cmd = cmd
        self.env = env
        """Variables set for this child on top of ``bgrl up``'s environment."""
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        preexec = _die_with_parent if sys.platform.startswith("linux") else None
        env = {**os.environ, **self.env} if self.env else None
        self.proc = subprocess.Popen(self.cmd, start_new_session=True, preexec_fn=preexec, env=env)

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def terminate(self) -> None:
        if self.alive():
            assert self.proc is not None
            self.proc.send_signal(signal.SIGTERM)

    def wait_or_kill(self, deadline: float) -> None:
        if self.proc is None:
            return
        try:
            self.proc.wait(timeout=max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            logger.warning("%s did not stop in time; killing it", self.name)
            self.proc.kill()
            self.proc.wait()


SERVICE_TOKEN_FILE = "service-token"
"""File in the data folder keeping the internal service token ``bgrl up`` generated."""


def kept_service_token(path: Path) -> str:
    """The token kept in ``path``, generated (URL-safe, 256 bits, mode 600) on first use."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        token = path.read_text().strip()
        if len(token) < 16:
            raise _fail(f"{path} holds no usable service token: delete it for a new one") from None
        return token
    token = secrets.token_urlsafe(32)
    with os.fdopen(fd, "w") as fh:
        fh.write(token + "\n")
    return token


def _fail(message: str) -> typer.Exit:
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(2)


def up(
    only: Annotated[
        list[str] | None,
        typer.Option(
            help="Start only these services: api, sim, eeg, learner, worker (repeatable)."
        ),
    ] = None,
    migrate: Annotated[
        bool, typer.Option(help="Bring the database to the current schema first.")
    ] = True,
) -> None:
    """Start the platform: api, sim, EEG, learner services and job workers; Ctrl-C stops all."""
    from services.core.logging import configure_log_file, configure_logging
    from services.core.platform import PlatformSettings

    known = {s.name for s in SERVICES} | {"worker"}
    if only and set(only) - known:
        raise _fail(f"--only: unknown {sorted(set(only) - known)}; known: {sorted(known)}")
    try:
        platform = load_settings(PlatformSettings)
        specs = [s for s in SERVICES if (not only or s.name in only) and s.available()]
        service_settings = [(spec, spec.load_settings()) for spec in specs]
        n_workers = platform.workers if not only or "worker" in only else 0
        if n_workers:
            from services.worker.settings import WorkerSettings

            load_settings(WorkerSettings)
    except SettingsError as exc:
        raise _fail(str(exc)) from None
    configure_logging(platform.log_level, json_lines=platform.log_json)
    configure_log_file(platform, "up")

    data_dir = platform.ensure_data_dir().resolve()
    typer.echo(f"data folder {data_dir}")
    if platform.service_token is None:
        # one door: sim, EEG and learner take calls only from the platform's own processes
        token_file = data_dir / SERVICE_TOKEN_FILE
        os.environ["BGRL_SERVICE_TOKEN"] = kept_service_token(token_file)
        typer.echo(f"internal services take the X-Service-Token kept in {token_file}")
    if migrate:
        from services.core.db.migrate import upgrade_database

        upgrade_database(platform.resolved_database_url)
        typer.echo("database schema up to date")

    services = [_service_child(spec, s) for spec, s in service_settings]
    worker_cmd = [sys.executable, "-m", "services.cli.main", "worker", "--no-migrate"]
    workers = [
        Child(f"worker-{i + 1}", [*worker_cmd, "--name", f"local{i + 1}"]) for i in range(n_workers)
    ]
    if not services and not workers:
        raise _fail("nothing to start")

    stop = threading.Event()

    def request_stop(signum: int, _frame: Any) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    exit_code = 0
    try:
        for child in [*services, *workers]:
            child.start()
        for spec, settings in service_settings:
            url = f"http://{settings.host}:{settings.port}"
            processes = getattr(settings, "api_workers", 1)
            extra = f", {processes} processes (BGRL_API_WORKERS)" if processes > 1 else ""
            typer.echo(f"{spec.name:>8}: {url}  (docs: {url}/docs{extra})")
        if workers:
            typer.echo(f"{'workers':>8}: {len(workers)} (BGRL_WORKERS)")
        typer.echo("Ctrl-C stops everything.")
        exit_code = _supervise(services, workers, stop)
    finally:
        deadline = time.monotonic() + STOP_TIMEOUT_S
        for child in [*workers, *services]:
            child.terminate()
        for child in [*workers, *services]:
            child.wait_or_kill(deadline)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        typer.echo("stopped")
    # Leave at once: nothing is left to clean up, and finalising the interpreter can take
    # seconds on a busy machine (Ctrl-C and SIGTERM must stop everything within 10 s).
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(exit_code)


def _service_child(spec: ServiceSpec, settings: BaseServiceSettings) -> Child:
    """The uvicorn process of one service; the api's with ``BGRL_API_WORKERS`` processes.

    The api processes do not migrate: ``bgrl up`` did it once before starting them (or was
    told not to), so several processes never run the migrations at the same moment.
    """
    cmd = [sys.executable, "-m", "uvicorn", spec.asgi_app]
    cmd += ["--host", settings.host, "--port", str(settings.port)]
    if spec.name != "api":
        return Child(spec.name, cmd)
    workers = getattr(settings, "api_workers", 1)
    if workers > 1:
        cmd += ["--workers", str(workers)]
    return Child(spec.name, cmd, env={"BGRL_MIGRATE_ON_START": "false"})


def _supervise(services: list[Child], workers: list[Child], stop: threading.Event) -> int:
    """Wait for a stop request; restart dead workers; return 1 if an HTTP service died."""
    restart_at: dict[str, float] = {}
    while not stop.wait(0.5):
        for child in services:
            if not child.alive():
                assert child.proc is not None
                typer.echo(
                    f"service {child.name} exited with code {child.proc.returncode}", err=True
                )
                return 1
        for child in workers:
            if child.alive():
                continue
            due = restart_at.setdefault(child.name, time.monotonic() + WORKER_RESTART_DELAY_S)
            if time.monotonic() >= due:
                assert child.proc is not None
                typer.echo(
                    f"{child.name} exited with code {child.proc.returncode}; restarting it",
                    err=True,
                )
                del restart_at[child.name]
                child.start()
    return 0


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``up`` and its alias ``serve`` to the ``bgrl`` command."""
    app.command("up")(up)
    app.command("serve", help="Alias of `bgrl up`.")(up)
