"""``bgrl serve``: start the platform's HTTP services on embedded defaults."""

from __future__ import annotations

import importlib.util
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from typing import Annotated

import typer


@dataclass(frozen=True)
class ServiceSpec:
    """One HTTP service the platform can start."""

    name: str
    asgi_app: str
    default_port: int

    @property
    def module(self) -> str:
        return self.asgi_app.split(":", 1)[0]

    def available(self) -> bool:
        """True when the service's module exists in this installation."""
        return importlib.util.find_spec(self.module) is not None


SERVICES = (
    ServiceSpec("sim", "services.sim.app:app", 8001),
    ServiceSpec("eeg", "services.eeg.app:app", 8002),
)


def serve(
    host: Annotated[str, typer.Option(help="Interface every service binds to.")] = "127.0.0.1",
    only: Annotated[
        list[str] | None, typer.Option(help="Start only these services (repeatable).")
    ] = None,
) -> None:
    """Start every available service as its own uvicorn process and wait; Ctrl-C stops all."""
    specs = [s for s in SERVICES if s.available() and (not only or s.name in only)]
    if not specs:
        raise typer.BadParameter(f"no service to start (known: {[s.name for s in SERVICES]})")
    procs: list[tuple[ServiceSpec, subprocess.Popen[bytes]]] = []
    for spec in specs:
        port = int(os.environ.get(f"BGRL_{spec.name.upper()}_PORT", spec.default_port))
        cmd = [sys.executable, "-m", "uvicorn", spec.asgi_app, "--host", host, "--port", str(port)]
        procs.append((spec, subprocess.Popen(cmd)))
        typer.echo(f"{spec.name:>8}: http://{host}:{port}  (docs: http://{host}:{port}/docs)")
    try:
        while all(p.poll() is None for _, p in procs):
            time.sleep(0.5)
        for spec, p in procs:
            if p.poll() is not None:
                typer.echo(f"service {spec.name} exited with code {p.returncode}", err=True)
        raise typer.Exit(1)
    except KeyboardInterrupt:
        typer.echo("stopping")
    finally:
        for _, p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for _, p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``serve`` to the ``bgrl`` command."""
    app.command("serve")(serve)
