"""``bgrl up`` (alias ``bgrl serve``): the whole platform on one machine, one command.

Every value comes from the services' settings (``BGRL_PORT``, ``BGRL_SIM_HOST``,
``BGRL_EEG_PORT``...), validated before anything starts: a bad one is one line naming the
variable. Then ``bgrl up`` binds every port itself (one in use: one line naming the variable
and the process holding it), creates the data folder, brings the database to the current
schema, creates the first admin, and starts the api (8000; ``BGRL_API_WORKERS`` processes
sharing its socket), sim (8001), EEG (8002) and learner (8003) services and ``BGRL_WORKERS``
job workers. Each process is told where the others are (``BGRL_SIM_URL``, ``BGRL_EEG_URL``,
``BGRL_LEARNER_URL``), derived from those same settings unless the variable is given.

:mod:`services.cli.supervisor` keeps them running (restart with backoff, health checks, a
crash loop stops that one process, or everything for the api) and every process dies with
``bgrl up``, even by SIGKILL. Ctrl-C or SIGTERM stops every process within 10 s (workers hand
their running job back to the queue); the data folder keeps the database, broker and
artifacts for the next start. The start-up ends with one block: dashboard, admin, data folder.
"""

from __future__ import annotations

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
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import typer

from services.core.settings import BaseServiceSettings, SettingsError, load_settings

logger = logging.getLogger("bgrl.up")

SERVICE_TOKEN_FILE = "service-token"
"""File in the data folder keeping the internal service token ``bgrl up`` generated."""
ADMIN_PASSWORD_FILE = "first-admin-password"
"""File in the data folder with the first admin's generated password (mode 600)."""
STATUS_FILE = "run/processes.json"
"""File in the data folder where ``bgrl up`` keeps its processes' state (for ``/readyz``)."""


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

    def variable(self, field: str) -> str:
        """The environment variable of one of its settings: ``BGRL_SIM_PORT``..."""
        module, _, name = self.settings_class.partition(":")
        cls = getattr(importlib.import_module(module), name)
        return f"{cls.model_config.get('env_prefix', '')}{field.upper()}"


SERVICES = (
    ServiceSpec("api", "services.api.app:app", "services.api.settings:ApiSettings"),
    ServiceSpec("sim", "services.sim.app:app", "services.sim.settings:SimSettings"),
    ServiceSpec("eeg", "services.eeg.service.app:app", "services.eeg.service.settings:EEGSettings"),
    ServiceSpec(
        "learner",
        "services.learner.service.app:app",
        "services.learner.service.settings:LearnerSettings",
    ),
)
CALLED_SERVICES = ("sim", "eeg", "learner")
"""Services the api and the workers call, each at ``BGRL_<NAME>_URL``."""


def url_variable(name: str) -> str:
    """``BGRL_SIM_URL`` for ``sim``: where the platform's processes find that service."""
    return f"BGRL_{name.upper()}_URL"


def connect_host(host: str) -> str:
    """The address to call a service listening on ``host`` (a wildcard: this machine)."""
    if host in ("", "0.0.0.0"):
        return "127.0.0.1"
    if host == "::":
        return "[::1]"
    return f"[{host}]" if ":" in host else host


def service_url(settings: BaseServiceSettings) -> str:
    """``http://host:port`` of a service from its settings."""
    return f"http://{connect_host(settings.host)}:{settings.port}"


def internal_urls(
    settings: Mapping[str, BaseServiceSettings], environ: Mapping[str, str]
) -> dict[str, str]:
    """``BGRL_SIM_URL``, ``BGRL_EEG_URL``, ``BGRL_LEARNER_URL``: as given in ``environ``,
    else derived from the service's own host and port settings (one source for both)."""
    urls = {}
    for name in CALLED_SERVICES:
        variable = url_variable(name)
        if variable in environ:
            urls[variable] = environ[variable]
        elif name in settings:
            urls[variable] = service_url(settings[name])
    return urls


class Child:
    """A child process that dies with this one (for commands that start a service or two)."""

    def __init__(self, name: str, cmd: list[str], env: dict[str, str] | None = None) -> None:
        self.name = name
        self.cmd = cmd
        self.env = env
        """Variables set for this child on top of this process's environment."""
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        from services.cli.supervisor import spawn_child

        self.proc = spawn_child(self.cmd, {**os.environ, **(self.env or {})})

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
    from services.api.settings import ApiSettings
    from services.cli.ports import PortError, bind_all
    from services.cli.supervisor import Supervisor, SupervisorSettings
    from services.core.logging import configure_log_file, configure_logging

    known = {s.name for s in SERVICES} | {"worker"}
    if only and set(only) - known:
        raise _fail(f"--only: unknown {sorted(set(only) - known)}; known: {sorted(known)}")
    try:
        platform = load_settings(ApiSettings)
        every = {spec.name: (spec, spec.load_settings()) for spec in SERVICES if spec.available()}
        started = [(spec, s) for spec, s in every.values() if not only or spec.name in only]
        n_workers = platform.workers if not only or "worker" in only else 0
        if n_workers:
            from services.worker.live_services import LiveSettings

            load_settings(LiveSettings)
        supervision = load_settings(SupervisorSettings)
    except SettingsError as exc:
        raise _fail(str(exc)) from None
    if not started and not n_workers:
        raise _fail("nothing to start")
    try:  # before anything starts: a port in use is one line naming who holds it
        sockets = bind_all([(spec.variable("port"), s.host, s.port) for spec, s in started])
    except PortError as exc:
        raise _fail(str(exc)) from None
    configure_logging(platform.log_level, json_lines=platform.log_json)
    configure_log_file(platform, "up")
    logging.getLogger("httpx").setLevel(logging.WARNING)  # not a line per health check

    data_dir = platform.ensure_data_dir().resolve()
    env = dict(os.environ)
    if platform.service_token is None:
        # one door: sim, EEG and learner take calls only from the platform's own processes
        env["BGRL_SERVICE_TOKEN"] = kept_service_token(data_dir / SERVICE_TOKEN_FILE)
    env.update(internal_urls({name: s for name, (_, s) in every.items()}, os.environ))
    if migrate:
        from services.core.db.migrate import upgrade_database

        upgrade_database(platform.resolved_database_url)
    status_file = data_dir / STATUS_FILE
    status_file.parent.mkdir(exist_ok=True)
    specs = []
    for (spec, settings), sock in zip(started, sockets, strict=True):
        specs += _service_processes(spec, settings, sock.fileno(), env, status_file)
    worker_cmd = [sys.executable, "-m", "services.cli.main", "worker", "--no-migrate"]
    specs += [_worker_process(i + 1, worker_cmd, env, status_file) for i in range(n_workers)]
    admin = _first_admin(platform, data_dir) if "api" in [s.name for s, _ in started] else None

    # the platform's side (api, workers) reaps jobs; a lone sim, EEG or learner has no database
    runs_jobs = n_workers > 0 or "api" in [s.name for s, _ in started]
    reaper = _reaper(platform) if runs_jobs else None

    def exited(spec: Any) -> None:
        if spec.kind == "worker" and reaper is not None:  # its taken messages died with it
            reaper.resend_queued_soon()

    supervisor = Supervisor(
        specs,
        supervision,
        status_file=status_file,
        echo=lambda line: typer.echo(line, err=True),
        on_exit=exited,
    )
    stop = threading.Event()

    def request_stop(signum: int, _frame: Any) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    exit_code = 0
    try:
        # the sockets stay open here: a restarted process serves the same one, and a port
        # never goes free (connections wait in its queue) while its service restarts
        supervisor.start()
        if reaper is not None:
            reaper.start()

        def ready(not_running: list[str]) -> None:
            typer.echo(_ready_block(started, n_workers, admin, data_dir, env, not_running))

        exit_code = supervisor.run(stop, ready)
    finally:
        if reaper is not None:
            reaper.stop()
        supervisor.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        typer.echo("stopped")
    # Leave at once: nothing is left to clean up, and finalising the interpreter can take
    # seconds on a busy machine (Ctrl-C and SIGTERM must stop everything within 10 s).
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(exit_code)


def _service_processes(
    spec: ServiceSpec,
    settings: BaseServiceSettings,
    fd: int,
    env: dict[str, str],
    status_file: Path,
) -> list[Any]:
    """The processes of one service, each serving the listening socket ``fd``: one, or the
    api's ``BGRL_API_WORKERS``. Each beats into ``<name>.beat`` beside the status file.

    The api processes do not migrate: ``bgrl up`` did it once before starting them (or was
    told not to), so several processes never run the migrations at the same moment.
    """
    from services.cli.supervisor import ProcessSpec

    cmd = [sys.executable, "-m", "services.cli.child", spec.asgi_app, "--fd", str(fd)]
    health = f"{service_url(settings)}/health"

    def heartbeat(name: str) -> tuple[list[str], Path]:
        beat = status_file.parent / f"{name}.beat"
        return ["--heartbeat", str(beat)], beat

    if spec.name != "api":  # the internal services are behind no proxy
        options, beat = heartbeat(spec.name)
        return [
            ProcessSpec(
                spec.name, spec.name, [*cmd, "--no-proxy-headers", *options], env, (fd,),
                health, heartbeat_file=beat,
            )
        ]  # fmt: skip
    cmd = [*cmd, *settings.uvicorn_proxy_options()]  # type: ignore[attr-defined]  # ApiSettings
    api_env = {
        **env,
        "BGRL_MIGRATE_ON_START": "false",
        "BGRL_SUPERVISOR_STATUS_FILE": str(status_file),
    }
    n = getattr(settings, "api_workers", 1)
    names = ["api"] if n == 1 else [f"api-{i + 1}" for i in range(n)]
    # processes sharing the port: a health check through it may reach a sibling, so each
    # one's own heartbeat says whether it is ready and alive
    shared_health = health if n == 1 else None
    processes = []
    for name in names:
        options, beat = heartbeat(name)
        processes.append(
            ProcessSpec(
                name, "api", [*cmd, *options], api_env, (fd,), shared_health,
                heartbeat_file=beat, essential=True,
            )
        )  # fmt: skip
    return processes


def _worker_process(number: int, cmd: list[str], env: dict[str, str], status_file: Path) -> Any:
    """A job worker, ready once it created its ready file beside the status file."""
    from services.cli.supervisor import ProcessSpec

    name = f"worker-{number}"
    ready = status_file.parent / f"{name}.ready"
    env = {**env, "BGRL_READY_FILE": str(ready)}
    return ProcessSpec(name, "worker", [*cmd, "--name", f"local{number}"], env, ready_file=ready)


def _reaper(settings: Any) -> Any:
    """The reaper of jobs whose worker died, in this process: whichever child dies (every
    worker included), a job left running is sent again or failed with the reason."""
    from services.core.db.session import make_engine, make_session_factory
    from services.core.queue import make_celery
    from services.core.reaper import Reaper

    sessions = make_session_factory(make_engine(settings.resolved_database_url))
    return Reaper(
        sessions,
        make_celery(settings),
        interval_s=settings.reaper_interval_s,
        stale_queued_s=settings.stale_queued_s,
    )


def _first_admin(settings: Any, data_dir: Path) -> str:
    """Create the first admin if there is no user; the block's lines about the admin."""
    from sqlalchemy import select

    from services.api.accounts import ensure_first_admin
    from services.core.db.models import User
    from services.core.db.session import make_engine, make_session_factory

    password_file = data_dir / ADMIN_PASSWORD_FILE
    engine = make_engine(settings.resolved_database_url)
    try:
        sessions = make_session_factory(engine)
        first = ensure_first_admin(sessions, settings, password_file=password_file)
        with sessions() as db:
            query = select(User.email).where(User.role == "admin", User.active).order_by(User.id)
            email = db.scalars(query).first()
    except Exception as exc:  # e.g. --no-migrate on a database without the schema
        return f"  admin        unknown ({type(exc).__name__}: is the database migrated?)"
    finally:
        engine.dispose()
    if email is None:
        return "  admin        none active: bgrl user create EMAIL --admin"
    lines = [f"  admin        {email}"]
    if first is not None and first.generated_password is None:
        lines.append("  password     the one in BGRL_ADMIN_PASSWORD")
    elif password_file.exists():
        lines.append(f"  password     in {password_file} (change it after signing in,")
        lines.append("               then delete the file)")
    else:
        lines.append(f"  password     as set (forgotten: bgrl user set-password {email})")
    return "\n".join(lines)


def _ready_block(
    started: list[tuple[ServiceSpec, BaseServiceSettings]],
    n_workers: int,
    admin: str | None,
    data_dir: Path,
    env: Mapping[str, str],
    not_running: list[str],
) -> str:
    """The block that ends the start-up: where to go, who signs in, where the data is."""
    by_name = {spec.name: settings for spec, settings in started}
    rule = "-" * 72
    lines = [rule, "bgrl is up" if not not_running else "bgrl is up, except: "
             + "; ".join(not_running)]  # fmt: skip
    if "api" in by_name:
        url = service_url(by_name["api"])
        lines.append(f"  dashboard    {url}/   (API docs: {url}/docs, state: {url}/readyz)")
    if admin:
        lines.append(admin)
    lines.append(f"  data folder  {data_dir}")
    others = [f"{spec.name} {service_url(s)}" for spec, s in started if spec.name != "api"]
    if n_workers:
        others.append(f"{n_workers} worker{'s' if n_workers > 1 else ''}")
    if others:
        lines.append(f"  services     {', '.join(others)}")
    called = [f"{v}={env[v]}" for v in map(url_variable, CALLED_SERVICES) if v in env]
    if called:
        lines.append(f"  wiring       {' '.join(called)}")
    lines += ["  Ctrl-C stops everything.", rule]
    return "\n".join(lines)


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``up`` and its alias ``serve`` to the ``bgrl`` command."""
    app.command("up")(up)
    app.command("serve", help="Alias of `bgrl up`.")(up)
