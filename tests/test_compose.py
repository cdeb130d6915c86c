"""docker-compose.yml and the Dockerfile, checked without Docker: every command of our image
is a real ``bgrl`` entry point with valid options, every environment variable is a field of
the settings class of the service that reads it, dependencies wait for health checks, and
volumes are named."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
import typer
import yaml
from pydantic.aliases import AliasChoices
from pydantic_settings import BaseSettings
from typer._click.exceptions import UsageError

from services.api.settings import ApiSettings
from services.cli.main import app
from services.eeg.settings import EEGSettings
from services.sim.settings import SimSettings
from services.worker.settings import WorkerSettings

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
SERVICES: dict[str, dict[str, Any]] = COMPOSE["services"]
OURS = {name: spec for name, spec in SERVICES.items() if "build" in spec}
SETTINGS: dict[str, type[BaseSettings]] = {
    "api": ApiSettings,
    "sim": SimSettings,
    "eeg": EEGSettings,
    "worker": WorkerSettings,
}


def env_names(cls: type[BaseSettings]) -> set[str]:
    """The environment variables a settings class reads."""
    prefix = cls.model_config.get("env_prefix", "")
    names = set()
    for name, field in cls.model_fields.items():
        alias = field.validation_alias
        if isinstance(alias, AliasChoices):
            names |= {c for c in alias.choices if isinstance(c, str) and c.isupper()}
        elif isinstance(alias, str):
            names.add(alias)
        else:
            names.add(f"{prefix}{name}".upper())
    return names


def check_entry_point(argv: list[str]) -> None:
    """``argv`` parses as a ``bgrl`` command line (options included) without running it;
    a wrong command or option raises ``UsageError``."""
    assert argv[0] == "bgrl", argv
    group = typer.main.get_command(app)
    with group.make_context("bgrl", list(argv[1:2])) as ctx:
        command = group.get_command(ctx, argv[1])
        if command is None:
            raise UsageError(f"No such command {argv[1]!r}")
        command.make_context(argv[1], list(argv[2:]), parent=ctx)  # options are checked here


def test_the_lab_stack_is_complete() -> None:
    assert set(SERVICES) == {"postgres", "redis", "api", "sim", "eeg", "worker", "flower"}
    assert set(OURS) == {"api", "sim", "eeg", "worker"}
    assert {spec["image"] for spec in OURS.values()} == {"bgrl:latest"}


@pytest.mark.parametrize("service", sorted(OURS))
def test_command_is_a_real_entry_point(service: str) -> None:
    check_entry_point(OURS[service]["command"])


def test_a_bad_option_would_be_caught() -> None:
    with pytest.raises(UsageError, match="No such option: --no-such-option"):
        check_entry_point(["bgrl", "worker", "--no-such-option"])
    with pytest.raises(UsageError, match="No such command 'no-such-command'"):
        check_entry_point(["bgrl", "no-such-command"])


@pytest.mark.parametrize("service", sorted(OURS))
def test_every_environment_variable_is_a_settings_field(service: str) -> None:
    variables = set(OURS[service]["environment"])
    unknown = variables - env_names(SETTINGS[service])
    assert not unknown, f"{service}: {sorted(unknown)} are not settings of {SETTINGS[service]}"


def test_the_check_of_variables_can_fail() -> None:
    assert "BGRL_SIM_PORT" in env_names(SimSettings)
    assert "BGRL_SIM_PORT" not in env_names(EEGSettings)
    assert "BGRL_BROKER_URL" in env_names(WorkerSettings)
    assert "BGRL_DATA_DIR" in env_names(SimSettings)


def test_api_and_workers_share_database_broker_and_artifacts() -> None:
    shared = ("BGRL_DATABASE_URL", "BGRL_BROKER_URL", "BGRL_ARTIFACT_DIR", "BGRL_SERVICE_TOKEN")
    api, worker = OURS["api"]["environment"], OURS["worker"]["environment"]
    assert all(api[var] == worker[var] for var in shared)
    assert api["BGRL_BROKER_URL"] == "redis://redis:6379/0"
    assert api["BGRL_DATABASE_URL"].startswith("postgresql+psycopg://bgrl:")
    assert api["BGRL_DATABASE_URL"].endswith("@postgres:5432/bgrl")
    artifacts = {"artifacts:/artifacts"}
    assert artifacts <= set(OURS["api"]["volumes"]) and artifacts <= set(OURS["worker"]["volumes"])


def test_services_listen_where_their_health_checks_and_clients_look() -> None:
    ports = {
        "api": OURS["api"]["environment"]["BGRL_PORT"],
        "sim": OURS["sim"]["environment"]["BGRL_SIM_PORT"],
        "eeg": OURS["eeg"]["environment"]["BGRL_EEG_PORT"],
    }
    for service, port in ports.items():
        check = " ".join(OURS[service]["healthcheck"]["test"])
        assert f"http://127.0.0.1:{port}/" in check, service
    hosts = {"api": "BGRL_HOST", "sim": "BGRL_SIM_HOST", "eeg": "BGRL_EEG_HOST"}
    assert all(OURS[s]["environment"][var] == "0.0.0.0" for s, var in hosts.items())
    assert OURS["api"]["environment"]["BGRL_EEG_URL"] == f"http://eeg:{ports['eeg']}"
    # One door: only the api publishes a port (Flower on loopback only).
    assert [s for s in OURS if "ports" in OURS[s]] == ["api"]
    assert all(p.startswith("127.0.0.1:") for p in SERVICES["flower"]["ports"])


def test_the_api_runs_several_processes_under_bgrl_up() -> None:
    api = OURS["api"]
    assert api["command"][:2] == ["bgrl", "up"]  # `bgrl up` passes --workers to uvicorn
    default = re.fullmatch(r"\$\{BGRL_API_WORKERS:-(\d+)\}", api["environment"]["BGRL_API_WORKERS"])
    assert default is not None
    assert ApiSettings(api_workers=int(default.group(1))).api_workers >= 2


def test_dependencies_wait_for_health_checks() -> None:
    for name, spec in SERVICES.items():
        for dependency, rule in spec.get("depends_on", {}).items():
            assert rule == {"condition": "service_healthy"}, (name, dependency)
            assert "healthcheck" in SERVICES[dependency], dependency
    assert set(OURS["worker"]["depends_on"]) == {"api", "redis"}  # the api migrates first
    assert "--no-migrate" in OURS["worker"]["command"]
    assert "--no-migrate" not in OURS["api"]["command"]


def test_workers_scale_and_volumes_are_named() -> None:
    worker = OURS["worker"]
    assert "container_name" not in worker and "ports" not in worker  # --scale worker=N
    declared = set(COMPOSE["volumes"])
    for name, spec in SERVICES.items():
        for mount in spec.get("volumes", []):
            source = mount.split(":", 1)[0]
            assert source in declared, f"{name}: {source} is not a named volume"


def test_dockerfile_runs_the_platform_with_settings_it_knows() -> None:
    dockerfile = (ROOT / "Dockerfile").read_text()
    cmd = re.search(r"^CMD (\[.*\])$", dockerfile, re.MULTILINE)
    assert cmd is not None
    check_entry_point(yaml.safe_load(cmd.group(1)))
    variables = set(re.findall(r"\b(BGRL_[A-Z_]+)=", dockerfile))
    assert variables == {"BGRL_DATA_DIR", "BGRL_ARTIFACT_DIR"}
    assert variables <= env_names(WorkerSettings) & env_names(ApiSettings)
    assert "torch==" not in dockerfile  # the version comes from pyproject.toml
