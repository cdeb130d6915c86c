"""docker-compose.yml run without Docker: each of its services as the same command with the
same environment in its own network namespace ("host"), the compose hostnames resolving to
the namespaces' addresses, PostgreSQL and Redis as real servers in theirs, two worker hosts
and a lab PC (this test's own requests). Each service runs with its image's install role
(tests/deploy/roles.py): the api without torch, pybullet or MNE.

What a container would give differently, and how it is given here: the named volumes are
folders (a volume several services mount, e.g. ``artifacts``, is one folder, as an NFS
share would be; each host's container paths are links to them), ``bgrl`` is this
interpreter's ``-m services.cli.main``, ``python`` in health checks is this interpreter,
the two worker replicas get ``BGRL_WORKER_NAME`` (a container's host name), the jobs'
lease timings are short so a lost host is noticed in seconds, and the free-space reserve is
the test suite's.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.deploy.netns import Lab, netns_unavailable
from tests.deploy.roles import ROOT, role_environment
from tests.helpers import env_without_bgrl

COMPOSE = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
DOT_ENV = {
    "POSTGRES_PASSWORD": "netns-test-password",
    "BGRL_SERVICE_TOKEN": "netns-test-service-token-0123456789",
    "BGRL_API_WORKERS": "1",  # the default 2 is for a lab server; this machine is shared
}
"""What a lab puts in .env beside docker-compose.yml."""
ROLES = {"api": "api"}
"""The install role of each service's image (Dockerfile targets); the rest: worker."""
TEST_TUNING = {
    "BGRL_JOB_LEASE_S": "6",
    "BGRL_JOB_HEARTBEAT_S": "0.5",
    "BGRL_REAPER_INTERVAL_S": "0.5",
    "BGRL_LIVE_RETRY_S": "120",
    "BGRL_LOG_JSON": "false",
}
"""Added to the workers' environment: a lost worker host is noticed in seconds."""
WORKER_HOSTS = ("worker-1", "worker-2")
PG_BIN = next(iter(sorted(Path("/usr/lib/postgresql").glob("*/bin"))), None)


def interpolate(value: str, variables: dict[str, str]) -> str:
    """Compose's ``${VAR}``, ``${VAR:-default}`` and ``${VAR:?error}`` in ``value``."""

    def one(match: re.Match[str]) -> str:
        name, op, arg = match.group(1), match.group(2), match.group(3)
        if variables.get(name):
            return variables[name]
        if op == ":?":
            raise KeyError(f"{name}: {arg}")
        return arg if op == ":-" else ""

    return re.sub(r"\$\{(\w+)(?:(:[-?])([^}]*))?\}", one, value)


def health_argv(spec: dict[str, Any]) -> list[str]:
    """A service's compose health check as a command line."""
    test = spec["healthcheck"]["test"]
    if test[0] == "CMD-SHELL":
        return ["sh", "-c", test[1]]
    argv = list(test[1:])
    return [sys.executable, *argv[1:]] if argv[0] == "python" else argv


def unavailable() -> str | None:
    reason = netns_unavailable()
    if reason is None and (PG_BIN is None or shutil.which("redis-server") is None):
        reason = "needs PostgreSQL's server (/usr/lib/postgresql/*/bin) and redis-server"
    if reason is None and subprocess.run(["id", "postgres"], capture_output=True).returncode:
        reason = "needs the postgres system user (PostgreSQL refuses to run as root)"
    return reason


class ComposeLab:
    """The compose services on namespace hosts: ``up()`` starts them in dependency order."""

    def __init__(self, root: Path, dot_env: dict[str, str] | None = None) -> None:
        self.root = root
        self.dot_env = {**DOT_ENV, **(dot_env or {})}  # the lab's .env
        self.lab = Lab(f"bgrl{os.getpid() % 100000}")
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.pg_dir = Path(tempfile.mkdtemp(prefix="bgrl-netns-pg-"))
        services = COMPOSE["services"]
        self.specs = {name: services[name] for name in services if name != "flower"}
        for name in ["lab-pc", *self.specs, *WORKER_HOSTS]:
            if name != "worker":
                self.lab.add_host(name)

    # ------------------------------------------------------------------ pieces
    def volume(self, name: str, host: str) -> Path:
        """The folder of named volume ``name``: one folder if several services mount it
        (an NFS share across hosts), else one per host (a replica's own volume)."""
        users = [s for s, spec in self.specs.items() if any(
            m.split(":", 1)[0] == name for m in spec.get("volumes", []))]  # fmt: skip
        folder = self.root / "volumes" / (name if len(users) > 1 else f"{name}@{host}")
        folder.mkdir(parents=True, exist_ok=True)
        return folder

    def filesystem(self, service: str, host: str) -> Path:
        """``host``'s container file system: a folder where each of ``service``'s mounts is
        a link to its volume folder (or to the repository file it binds)."""
        root = self.root / "hosts" / host
        mounts = []
        for mount in self.specs[service].get("volumes", []):
            source, rest = mount.split("}", 1) if mount.startswith("${") else ("", mount)
            first, target, *_ = rest.split(":")
            path = ROOT / interpolate(source + "}" + first, self.dot_env) if source else None
            mounts.append((target, path or self.volume(first, host)))
        for target, path in sorted(mounts, key=lambda m: m[0].count("/")):
            link = root / target.lstrip("/")  # through an outer mount's link, as nested
            link.parent.mkdir(parents=True, exist_ok=True)
            if not link.is_symlink():
                link.symlink_to(path)
        return root

    def environment(self, service: str, host: str) -> dict[str, str]:
        """The service's compose environment, container paths put in the host's file
        system, plus its role's import limits and (workers) the test's lease timings."""
        root = self.filesystem(service, host)
        env = {}
        for key, value in self.specs[service].get("environment", {}).items():
            value = interpolate(str(value), self.dot_env)
            env[key] = str(root) + value if value.startswith("/") else value
        # the test suite's free-space reserve (tests/conftest.py), not a lab's 1 GB
        env["BGRL_MIN_FREE_MB"] = os.environ.get("BGRL_MIN_FREE_MB", "1")
        if service == "worker":
            env |= {**TEST_TUNING, "BGRL_WORKER_NAME": host}
        role = ROLES.get(service, "worker")
        return {**env_without_bgrl(), **role_environment(role, self.root / "roles" / role), **env}

    def argv(self, service: str) -> list[str]:
        command = [interpolate(str(a), self.dot_env) for a in self.specs[service]["command"]]
        assert command[0] == "bgrl", command
        return [sys.executable, "-m", "services.cli.main", *command[1:]]

    def log(self, host: str) -> Path:
        return self.root / f"{host}.log"

    def tail(self, host: str, chars: int = 4000) -> str:
        path = self.log(host)
        return path.read_text(errors="replace")[-chars:] if path.exists() else "(no log)"

    # ------------------------------------------------------------------ servers
    def start_postgres(self) -> None:
        """A private PostgreSQL with compose's user, password and database."""
        assert PG_BIN is not None
        data = self.pg_dir / "data"
        if not data.exists():
            shutil.chown(self.pg_dir, "postgres", "postgres")
            pwfile = self.pg_dir / "pw"
            pwfile.write_text(self.dot_env["POSTGRES_PASSWORD"] + "\n")
            shutil.chown(pwfile, "postgres", "postgres")
            subprocess.run(
                ["runuser", "-u", "postgres", "--", str(PG_BIN / "initdb"), "-D", str(data),
                 "-U", "bgrl", "--pwfile", str(pwfile), "--auth=scram-sha-256"],
                check=True, capture_output=True,
            )  # fmt: skip
            with (data / "postgresql.conf").open("a") as conf:
                conf.write("fsync = off\nsynchronous_commit = off\nfull_page_writes = off\n")
            (data / "pg_hba.conf").write_text("host all all 0.0.0.0/0 scram-sha-256\n")
            created = True
        else:
            created = False
        command = list(self.specs["postgres"].get("command", ["postgres"]))  # compose's
        assert command[0] == "postgres", command
        self.procs["postgres"] = self.lab.start(
            "postgres",
            [str(PG_BIN / "postgres"), *command[1:], "-D", str(data), "-p", "5432",
             "-c", "listen_addresses=*", "-c", f"unix_socket_directories={self.pg_dir}"],
            env={"PATH": os.environ["PATH"]}, log=self.log("postgres"), cwd=self.pg_dir,
            user="postgres",
        )  # fmt: skip
        pg_env = {"PATH": os.environ["PATH"], "PGHOST": "127.0.0.1",
                  "PGPASSWORD": self.dot_env["POSTGRES_PASSWORD"]}  # fmt: skip
        self.wait_until("postgres", lambda: self.lab.run(
            "postgres", [str(PG_BIN / "pg_isready"), "-U", "bgrl", "-d", "postgres"], pg_env
        ).returncode == 0)  # fmt: skip
        if created:
            createdb = [str(PG_BIN / "createdb"), "-U", "bgrl", "bgrl"]
            done = self.lab.run("postgres", createdb, pg_env)
            assert done.returncode == 0, done.stderr
        check = health_argv(self.specs["postgres"])  # compose's own check: pg_isready
        check[-1] = check[-1].replace("pg_isready", str(PG_BIN / "pg_isready"))
        self.wait_until("postgres", lambda: self.lab.run("postgres", check, pg_env).returncode == 0)

    def start_redis(self) -> None:
        """Redis with compose's command (append-only file), in its namespace."""
        command = list(self.specs["redis"]["command"])
        folder = self.volume("redisdata", "redis")
        command += ["--port", "6379", "--bind", "0.0.0.0", "--protected-mode", "no",
                    "--save", "", "--dir", str(folder)]  # fmt: skip
        self.procs["redis"] = self.lab.start(
            "redis", command, env={"PATH": os.environ["PATH"]}, log=self.log("redis"), cwd=folder
        )
        check = health_argv(self.specs["redis"])
        self.wait_until("redis", lambda: self.lab.run("redis", check).returncode == 0)

    # ------------------------------------------------------------------ ours
    def start(self, service: str, host: str | None = None) -> None:
        host = host or service
        self.procs[host] = self.lab.start(
            host, self.argv(service), env=self.environment(service, host), log=self.log(host),
            cwd=self.root,
        )  # fmt: skip

    def wait_healthy(self, service: str, timeout: float = 180.0) -> None:
        check = health_argv(self.specs[service])
        env = {"PATH": os.environ["PATH"]}
        self.wait_until(service, lambda: self.lab.run(service, check, env).returncode == 0, timeout)

    def wait_until(self, host: str, ready: Callable[[], bool], timeout: float = 180.0) -> None:
        deadline = time.monotonic() + timeout
        while not ready():
            proc = self.procs.get(host)
            if (proc is not None and proc.poll() is not None) or time.monotonic() > deadline:
                state = "exited" if proc is not None and proc.poll() is not None else "not ready"
                pytest.fail(f"{host} {state}:\n{self.tail(host)}")
            time.sleep(0.3)

    def up(self) -> None:
        """Start every service in compose's order, as ``docker compose up`` does: in
        rounds, each service once every one it ``depends_on`` passed its health check, the
        services of a round together; ``worker`` on every worker host."""
        healthy: set[str] = set()
        while len(healthy) < len(self.specs):
            ready = [
                name for name, spec in self.specs.items()
                if name not in healthy and set(spec.get("depends_on", {})) <= healthy
            ]  # fmt: skip
            assert ready, f"a dependency cycle among {set(self.specs) - healthy}"
            for service in ready:
                if service == "postgres":
                    self.start_postgres()
                elif service == "redis":
                    self.start_redis()
                elif service == "worker":
                    for host in WORKER_HOSTS:
                        self.start("worker", host)
                else:
                    self.start(service)
            for service in ready:
                if service not in {"postgres", "redis", "worker"}:  # those waited above
                    self.wait_healthy(service)
            healthy.update(ready)

    def kill(self, host: str, sig: int = signal.SIGKILL) -> None:
        self.lab.stop(self.procs.pop(host), sig)

    def close(self) -> None:
        self.lab.close()
        shutil.rmtree(self.pg_dir, ignore_errors=True)


@pytest.fixture(scope="module")
def compose_lab(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ComposeLab]:
    reason = unavailable()
    if reason is not None:
        pytest.skip(f"the namespace deployment {reason}")
    lab = None
    try:
        lab = ComposeLab(tmp_path_factory.mktemp("compose"))
        yield lab
    finally:
        if lab is not None:
            lab.close()
