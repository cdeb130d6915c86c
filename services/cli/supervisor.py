"""The supervisor of ``bgrl up``: restarts what dies or stops answering, gives up on a crash loop.

Each :class:`Supervised` process is restarted when it exits, after a backoff that doubles
with every recent exit (1 s, 2 s, 4 s... at most 30 s). One whose ``health_url`` has not
answered for ``health_timeout_s`` is stopped and restarted the same way, and so is one whose
``heartbeat_file`` (touched every second by its event loop, see
:mod:`services.cli.child`) is older than ``heartbeat_timeout_s``: a hung process is found
even among several sharing one port, where a health check may reach a sibling. A hung
process gets SIGKILL at once (its loop would not handle SIGTERM). ``restart_limit``
exits within ``restart_window_s`` is a crash loop: the process is stopped for good with a
one-line reason, and the rest stay up, unless it is ``essential`` (nothing works without
it): then everything stops. Every change is logged and written to ``status_file`` (JSON),
which the api's ``/readyz`` reports.

Every child gets ``PR_SET_PDEATHSIG`` (:func:`services.core.lifetime.die_with_parent`): a
SIGKILL of ``bgrl up`` ends them all.
"""

from __future__ import annotations

import functools
import os
import signal
import subprocess
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import httpx
from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from services.core.files import write_json_atomic
from services.core.lifetime import die_with_parent
from services.core.settings import ENV_PREFIX

STOP_TIMEOUT_S = 7.0
"""Seconds a child gets to stop after SIGTERM before it is killed (all stop within 10 s)."""
FIRST_BACKOFF_S = 1.0
MAX_BACKOFF_S = 30.0
TICK_S = 0.25
"""Seconds between two looks at the children."""


class SupervisorSettings(BaseSettings):
    """How ``bgrl up`` supervises its processes (``BGRL_`` environment variables)."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="ignore")

    restart_limit: int = Field(
        5,
        ge=1,
        le=1000,
        description="Exits of one process within restart_window_s that "
        "make a crash loop: the process is stopped for good (everything, for the api).",
    )
    restart_window_s: float = Field(60.0, gt=0, description="See restart_limit.")
    health_interval_s: float = Field(
        2.0, gt=0, description="Seconds between two health checks of each HTTP service."
    )
    health_timeout_s: float = Field(
        30.0,
        gt=0,
        description="An HTTP service whose health check has not answered for "
        "this long is restarted.",
    )
    heartbeat_timeout_s: float = Field(
        15.0,
        gt=0,
        description="An HTTP service process whose event loop has not beaten for this long "
        "(hung, or stopped) is killed and restarted; it is restarted within this time plus "
        "its start.",
    )
    start_timeout_s: float = Field(
        120.0,
        gt=0,
        description="Seconds a (re)started HTTP service has to answer its "
        "first health check before it is restarted.",
    )


@dataclass(frozen=True)
class ProcessSpec:
    """One process to keep running."""

    name: str
    """Unique name in logs and the status (``api``, ``api-2``, ``sim``, ``worker-1``...)."""
    kind: str
    """``api``, ``sim``, ``eeg``, ``learner`` or ``worker``."""
    cmd: list[str]
    env: dict[str, str]
    """The child's whole environment."""
    pass_fds: tuple[int, ...] = ()
    health_url: str | None = None
    ready_file: Path | None = None
    """For a process without health URL: the file it creates once ready (a worker)."""
    heartbeat_file: Path | None = None
    """The file its event loop touches every second (an HTTP service process): it is ready
    once the file exists (without a health URL), and hung once it is older than
    ``heartbeat_timeout_s``."""
    essential: bool = False
    """Nothing works without it: its crash loop stops everything."""


@dataclass
class Supervised:
    """A process under supervision and what happened to it."""

    spec: ProcessSpec
    proc: subprocess.Popen[bytes] | None = None
    state: str = "starting"
    """``starting`` (not ready yet), ``running``, ``restarting`` (from an exit until it is
    ready again) or ``stopped`` (a crash loop)."""
    restarts: int = 0
    exits: deque[float] = field(default_factory=deque)
    """When it exited (or was restarted for its health) within the restart window."""
    started_at: float = 0.0
    healthy_at: float | None = None
    restart_at: float | None = None
    last_exit: str | None = None
    reason: str | None = None
    since: str = ""

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def status(self) -> dict[str, Any]:
        return {
            "kind": self.spec.kind,
            "state": self.state,
            "pid": self.proc.pid if self.alive() and self.proc is not None else None,
            "restarts": self.restarts,
            "last_exit": self.last_exit,
            "reason": self.reason,
            "since": self.since,
        }


def spawn_child(
    cmd: list[str], env: dict[str, str] | None = None, pass_fds: tuple[int, ...] = ()
) -> subprocess.Popen[bytes]:
    """Start ``cmd`` in its own session (Ctrl-C reaches ``bgrl up`` alone, which stops the
    children) with SIGTERM as its parent-death signal: it ends with this process."""
    return subprocess.Popen(
        cmd,
        env=env,
        pass_fds=pass_fds,
        start_new_session=True,
        preexec_fn=functools.partial(die_with_parent, os.getpid(), signal.SIGTERM),
    )


def exit_text(code: int) -> str:
    """``code 1`` or ``signal SIGKILL`` for a Popen return code."""
    if code < 0:
        with_name = signal.Signals(-code).name if -code in signal.valid_signals() else -code
        return f"code {code} ({with_name})"
    return f"code {code}"


class Supervisor:
    """Starts, watches and stops a set of processes (see the module's docstring)."""

    def __init__(
        self,
        specs: list[ProcessSpec],
        settings: SupervisorSettings,
        *,
        status_file: Path | None = None,
        echo: Callable[[str], None] = print,
        on_exit: Callable[[ProcessSpec], None] | None = None,
    ) -> None:
        names = [spec.name for spec in specs]
        if len(set(names)) != len(names):
            raise ValueError(f"process names must be unique: {names}")
        self.processes = [Supervised(spec) for spec in specs]
        self.settings = settings
        self.status_file = status_file
        self.echo = echo
        self.on_exit = on_exit
        """Called with a process's spec whenever it exited or was stopped for its health."""
        self.fatal: str | None = None
        """Why everything stops (an essential process's crash loop), once it happened."""
        self._lock = threading.Lock()
        self._checker = threading.Thread(target=self._check_health, name="health", daemon=True)
        self._done = threading.Event()

    # -- start and stop -------------------------------------------------------------------

    def start(self) -> None:
        """Start every process and the health checks."""
        for process in self.processes:
            self._spawn(process)
        self._write_status()
        self._checker.start()

    def _spawn(self, process: Supervised) -> None:
        spec = process.spec
        for marker in (spec.ready_file, spec.heartbeat_file):
            if marker is not None:
                marker.unlink(missing_ok=True)
        process.proc = spawn_child(spec.cmd, spec.env, spec.pass_fds)
        with self._lock:
            process.started_at = time.monotonic()
            process.healthy_at = None
        process.restart_at = None
        waits = spec.health_url or spec.ready_file or spec.heartbeat_file
        process.state = "starting" if waits else "running"
        process.since = _now()

    def stop(self) -> None:
        """SIGTERM to every process, SIGKILL to those still there after ``STOP_TIMEOUT_S``."""
        self._done.set()
        deadline = time.monotonic() + STOP_TIMEOUT_S
        # workers first in the list: they hand their job back while the services still run
        ordered = sorted(self.processes, key=lambda p: p.spec.kind != "worker")
        for process in ordered:
            if process.alive():
                assert process.proc is not None
                process.proc.send_signal(signal.SIGTERM)
        for process in ordered:
            self._wait_or_kill(process, deadline)

    def _wait_or_kill(self, process: Supervised, deadline: float) -> None:
        if process.proc is None:
            return
        try:
            process.proc.wait(timeout=max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            self.echo(f"{process.spec.name} did not stop in time; killing it")
            process.proc.kill()
            process.proc.wait()

    # -- watching -------------------------------------------------------------------------

    def run(self, stop: threading.Event, on_ready: Callable[[list[str]], None]) -> int:
        """Watch until ``stop`` is set (0) or an essential process gives up (1).

        ``on_ready(not_running)`` is called once, when no process is starting or restarting
        any more (every HTTP service answered its health check, every worker is ready), or
        after ``start_timeout_s``; ``not_running`` says which are not, and why.
        """
        ready_by = time.monotonic() + self.settings.start_timeout_s
        announced = False
        while not stop.wait(TICK_S):
            changed = False
            for process in self.processes:
                changed |= self._look_at(process)
            if changed:
                self._write_status()
            if self.fatal is not None:
                return 1
            if not announced:
                pending = any(p.state in ("starting", "restarting") for p in self.processes)
                if not pending or time.monotonic() > ready_by:
                    announced = True
                    on_ready(
                        [
                            f"{p.spec.name} ({p.reason or p.state})"
                            for p in self.processes
                            if p.state != "running"
                        ]
                    )
        return 0

    def _look_at(self, process: Supervised) -> bool:
        """Restart, give up or mark healthy; True if the process's state changed."""
        if process.state == "stopped":
            return False
        now = time.monotonic()
        if process.restart_at is not None:
            if now < process.restart_at:
                return False
            self._spawn(process)
            process.restarts += 1
            if process.state == "starting":  # restarting until it answers again
                process.state = "restarting"
            return True
        if not process.alive():
            assert process.proc is not None
            return self._exited(process, exit_text(process.proc.returncode))
        spec = process.spec
        if (hung := self._missed_heartbeat(process)) is not None:
            return self._unhealthy(process, hung, kill=True)
        if spec.health_url is None:
            return self._look_for_ready_file(process, now)
        with self._lock:
            healthy_at = process.healthy_at
        if healthy_at is not None and healthy_at >= process.started_at:
            if process.state != "running":
                process.state = "running"
                return True
            if now - healthy_at > self.settings.health_timeout_s:
                return self._unhealthy(
                    process,
                    f"no answer from {spec.health_url} for {self.settings.health_timeout_s:g} s",
                )
        elif now - process.started_at > self.settings.start_timeout_s:
            return self._unhealthy(
                process,
                f"no answer from {spec.health_url} within "
                f"{self.settings.start_timeout_s:g} s of its start",
            )
        return False

    def _missed_heartbeat(self, process: Supervised) -> str | None:
        """Why the process is hung (its heartbeat file too old), or None."""
        beat = process.spec.heartbeat_file
        if beat is None:
            return None
        try:
            age = time.time() - beat.stat().st_mtime
        except FileNotFoundError:  # not serving yet: the start timeout applies
            return None
        if age <= self.settings.heartbeat_timeout_s:
            return None
        return f"no heartbeat for {age:.0f} s (its event loop does not run)"

    def _look_for_ready_file(self, process: Supervised, now: float) -> bool:
        ready_file = process.spec.ready_file or process.spec.heartbeat_file
        if ready_file is None or process.state not in ("starting", "restarting"):
            return False
        if ready_file.exists():
            process.state = "running"
            return True
        if now - process.started_at > self.settings.start_timeout_s:
            return self._unhealthy(
                process, f"not ready within {self.settings.start_timeout_s:g} s of its start"
            )
        return False

    def _unhealthy(self, process: Supervised, why: str, *, kill: bool = False) -> bool:
        """Stop a process that does not answer (SIGTERM, SIGKILL after ``STOP_TIMEOUT_S``;
        ``kill``: SIGKILL at once) and count it as an exit."""
        self.echo(f"{process.spec.name}: {why}; {'killing' if kill else 'stopping'} it")
        assert process.proc is not None
        if kill:
            process.proc.kill()
            process.proc.wait()
        else:
            process.proc.send_signal(signal.SIGTERM)
            process.proc.send_signal(signal.SIGCONT)  # a stopped process handles it too
            self._wait_or_kill(process, time.monotonic() + STOP_TIMEOUT_S)
        return self._exited(process, why)

    def _exited(self, process: Supervised, what: str) -> bool:
        """Count the exit; schedule the restart or give up."""
        now = time.monotonic()
        window = self.settings.restart_window_s
        process.exits.append(now)
        while process.exits and now - process.exits[0] > window:
            process.exits.popleft()
        process.last_exit = what
        process.since = _now()
        if self.on_exit is not None:
            self.on_exit(process.spec)
        name = process.spec.name
        if len(process.exits) >= self.settings.restart_limit:
            process.state = "stopped"
            process.reason = (
                f"crash loop: {len(process.exits)} exits in {window:g} s (last: {what})"
            )
            if process.spec.essential:
                self.fatal = (
                    f"{name}: {process.reason}; stopping everything "
                    f"(nothing works without the {process.spec.kind})"
                )
                self.echo(self.fatal)
            else:
                self.echo(f"{name}: {process.reason}; stopped, the other processes stay up")
            return True
        delay = min(FIRST_BACKOFF_S * 2 ** (len(process.exits) - 1), MAX_BACKOFF_S)
        process.state = "restarting"
        process.restart_at = now + delay
        self.echo(
            f"{name} exited with {what}; restarting it in {delay:g} s "
            f"(restart {process.restarts + 1})"
        )
        return True

    def _check_health(self) -> None:
        """Thread: ask every HTTP service's health URL each ``health_interval_s``."""
        interval = self.settings.health_interval_s
        with httpx.Client(timeout=interval) as client:
            while not self._done.wait(interval):
                for process in self.processes:
                    url = process.spec.health_url
                    if url is None or not process.alive():
                        continue
                    asked = time.monotonic()
                    try:
                        ok = client.get(url).status_code == 200
                    except httpx.HTTPError:
                        ok = False
                    if ok:
                        with self._lock:
                            process.healthy_at = asked

    # -- status ---------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """What the status file holds: every process's state, restarts and last exit."""
        return {
            "supervisor_pid": os.getpid(),
            "updated_at": _now(),
            "processes": {p.spec.name: p.status() for p in self.processes},
        }

    def _write_status(self) -> None:
        if self.status_file is not None:
            write_json_atomic(self.status_file, self.status())


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")
