"""The install roles of pyproject.toml hold: the api serves and the client signs in with
only their own extras' packages importable (no torch, pybullet or MNE). Each runs in a
subprocess whose ``sitecustomize`` makes every package outside its role unimportable
(tests/deploy/roles.py), as in an install of that role alone (the Dockerfile's ``client``
and ``api`` targets); the namespace deployment (test_compose_netns.py) runs every compose
service with its image's role too."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from tests.deploy.roles import (
    blocked_modules,
    installed_closure,
    role_environment,
    role_requirements,
)
from tests.helpers import env_without_bgrl, free_port, stop_processes, wait_healthy

HEAVY = {"torch", "pybullet", "mne", "mne_lsl", "mne_bids", "scipy", "sklearn"}
SERVER = {"fastapi", "uvicorn", "sqlalchemy", "celery", "alembic", "argon2", "jwt"}
ADMIN_EMAIL = "admin@lab.test"
ADMIN_PASSWORD = "admin-password-123"


def run_as(role: str, folder: Path, argv: list[str], **kwargs: object):
    env = {**env_without_bgrl(), **role_environment(role, folder / role), **kwargs.pop("env", {})}  # type: ignore[dict-item]
    return subprocess.run(
        [sys.executable, *argv], env=env, capture_output=True, text=True, timeout=120, **kwargs
    )  # type: ignore[call-overload]


def test_each_role_leaves_out_what_it_does_not_run() -> None:
    assert blocked_modules("client") >= HEAVY | SERVER
    assert blocked_modules("api") >= HEAVY and not SERVER & blocked_modules("api")
    assert not HEAVY & blocked_modules("services")
    assert not (HEAVY | SERVER) & blocked_modules("worker")
    # `make install` (.[dev]) still installs everything the roles do
    every_role = set().union(*(installed_closure(role_requirements(r)) for r in ("api", "worker")))
    assert every_role <= installed_closure(role_requirements("dev"))


def test_the_check_can_fail(tmp_path: Path) -> None:
    """A module of another role is refused by name in a role's process."""
    for module in ("services.sim.app", "torch", "pybullet", "mne"):
        done = run_as("api", tmp_path, ["-c", f"import {module}"])
        assert done.returncode != 0, module
        assert "No module named" in done.stderr, done.stderr[-2000:]


def test_the_api_serves_and_the_client_signs_in_without_the_science_stack(
    tmp_path: Path,
) -> None:
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    api_env = {
        **env_without_bgrl(),
        **role_environment("api", tmp_path / "api"),
        "BGRL_DATA_DIR": str(tmp_path / "data"),
        "BGRL_PORT": str(port),
        "BGRL_EEG_URL": "",
        "BGRL_SIM_URL": "",
        "BGRL_ADMIN_EMAIL": ADMIN_EMAIL,
        "BGRL_ADMIN_PASSWORD": ADMIN_PASSWORD,
    }
    log = tmp_path / "api.log"
    api = subprocess.Popen(
        [sys.executable, "-m", "services.cli.main", "up", "--only", "api"],
        env=api_env, stdout=log.open("wb"), stderr=subprocess.STDOUT, cwd=tmp_path,
    )  # fmt: skip
    try:
        wait_healthy(url, api, log, timeout_s=90, path="/readyz")
        client = {"BGRL_CREDENTIALS_FILE": str(tmp_path / "credentials.json")}
        login = ["-m", "services.cli.main", "login", "--url", url, "--email", ADMIN_EMAIL,
                 "--password-stdin"]  # fmt: skip
        done = run_as("client", tmp_path, login, input=ADMIN_PASSWORD + "\n", env=client)
        assert done.returncode == 0, done.stderr[-3000:]
        done = run_as("client", tmp_path, ["-m", "services.cli.main", "jobs", "list", "--json"],
                      env=client)  # fmt: skip
        assert done.returncode == 0, done.stderr[-3000:]
        assert json.loads(done.stdout)["items"] == []
    finally:
        stop_processes([api])
    assert "No module named" not in log.read_text()
