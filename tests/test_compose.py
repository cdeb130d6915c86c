"""docker-compose.yml and the Dockerfile, checked without Docker: every command of our images
is a real ``bgrl`` entry point with valid options, every environment variable is a field of
the settings class of the service that reads it, every internal URL names a compose service
at the port it listens on, dependencies wait for health checks, and volumes are named.
tests/deploy runs the same file across network namespaces."""

from __future__ import annotations

import configparser
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
from services.core.platform import PlatformSettings
from services.eeg.service.settings import EEGSettings
from services.learner.service.settings import LearnerSettings
from services.sim.settings import SimSettings
from services.worker.live_services import LiveSettings
from services.worker.settings import WorkerSettings

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
SERVICES: dict[str, dict[str, Any]] = COMPOSE["services"]
OURS = {name: spec for name, spec in SERVICES.items() if "build" in spec}
SETTINGS: dict[str, tuple[type[BaseSettings], ...]] = {
    "api": (ApiSettings,),
    "sim": (SimSettings,),
    "eeg": (EEGSettings,),
    "learner": (LearnerSettings, PlatformSettings),  # the artifact store it exports into
    "worker": (LiveSettings,),
}
LIBRARY_VARIABLES = {"eeg": {"LSLAPICFG"}}
"""Variables read by a library, not by our settings (liblsl's configuration file)."""
PORT_VARIABLES = {
    "api": "BGRL_PORT",
    "sim": "BGRL_SIM_PORT",
    "eeg": "BGRL_EEG_PORT",
    "learner": "BGRL_LEARNER_PORT",
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


def mount_parts(mount: str) -> list[str]:
    """A short-syntax volume as [source, target, options...]; a source may be
    ``${VARIABLE:-default}``."""
    source, rest = mount.split("}", 1) if mount.startswith("${") else ("", mount)
    first, *others = rest.split(":")
    return [source + "}" + first if source else first, *others]


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
    assert set(SERVICES) == {
        "postgres", "redis", "api", "sim", "eeg", "learner", "worker", "flower",
    }  # fmt: skip
    assert set(OURS) == {"api", "sim", "eeg", "learner", "worker"}
    targets = {name: spec["build"]["target"] for name, spec in OURS.items()}
    assert targets == {"api": "api", "sim": "platform", "eeg": "platform",
                       "learner": "platform", "worker": "platform"}  # fmt: skip
    assert OURS["api"]["image"] != OURS["worker"]["image"]  # one image a target


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
    known = set().union(*(env_names(cls) for cls in SETTINGS[service]))
    unknown = variables - known - LIBRARY_VARIABLES.get(service, set())
    assert not unknown, f"{service}: {sorted(unknown)} are not settings of {SETTINGS[service]}"


def test_the_check_of_variables_can_fail() -> None:
    assert "BGRL_SIM_PORT" in env_names(SimSettings)
    assert "BGRL_SIM_PORT" not in env_names(EEGSettings)
    assert "BGRL_BROKER_URL" in env_names(WorkerSettings)
    assert "BGRL_LEARNER_URL" in env_names(LiveSettings)
    assert "BGRL_LEARNER_URL" not in env_names(WorkerSettings)
    assert "BGRL_LEARNER_PORT" in env_names(LearnerSettings)
    assert "BGRL_DATA_DIR" in env_names(SimSettings)


def test_api_and_workers_share_database_broker_and_artifacts() -> None:
    shared = ("BGRL_DATABASE_URL", "BGRL_BROKER_URL", "BGRL_ARTIFACT_DIR", "BGRL_SERVICE_TOKEN")
    api, worker = OURS["api"]["environment"], OURS["worker"]["environment"]
    assert all(api[var] == worker[var] for var in shared)
    assert api["BGRL_BROKER_URL"] == "redis://redis:6379/0"
    assert api["BGRL_DATABASE_URL"].startswith("postgresql+psycopg://bgrl:")
    assert api["BGRL_DATABASE_URL"].endswith("@postgres:5432/bgrl")
    artifacts = {"artifacts:/artifacts"}
    # the learner service writes an online session's pi_HF into the same store
    for service in ("api", "worker", "learner"):
        assert artifacts <= set(OURS[service]["volumes"]), service
        assert OURS[service]["environment"]["BGRL_ARTIFACT_DIR"] == "/artifacts", service


def test_services_listen_where_their_health_checks_and_clients_look() -> None:
    ports = {s: OURS[s]["environment"][var] for s, var in PORT_VARIABLES.items()}
    for service, port in ports.items():
        check = " ".join(OURS[service]["healthcheck"]["test"])
        assert f"http://127.0.0.1:{port}/" in check, service
        host = PORT_VARIABLES[service].replace("_PORT", "_HOST")
        assert OURS[service]["environment"][host] == "0.0.0.0", service
    # every internal URL set explicitly, naming the service at the port it listens on
    internal = ("sim", "eeg", "learner")
    expected = {f"BGRL_{s.upper()}_URL": f"http://{s}:{ports[s]}" for s in internal}
    worker = OURS["worker"]["environment"]
    assert {var: worker.get(var) for var in expected} == expected
    api = OURS["api"]["environment"]
    assert {var: api[var] for var in expected if var in env_names(ApiSettings)} == {
        var: url for var, url in expected.items() if var != "BGRL_LEARNER_URL"
    }
    # One door: only the api publishes a TCP port (Flower on loopback only); the EEG service
    # takes only liblsl's answers to its stream queries (docs/deploy.md, LSL on a lab LAN)
    assert [s for s in OURS if "ports" in OURS[s]] == ["api", "eeg"]
    assert OURS["eeg"]["ports"] == ["16572-16603:16572-16603/udp"]
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
    # the api migrates first; live sessions need sim, EEG and learner up
    assert set(OURS["worker"]["depends_on"]) == {"api", "redis", "sim", "eeg", "learner"}
    assert "--no-migrate" in OURS["worker"]["command"]
    assert "--no-migrate" not in OURS["api"]["command"]


def test_workers_scale_and_volumes_are_named() -> None:
    worker = OURS["worker"]
    assert "container_name" not in worker and "ports" not in worker  # --scale worker=N
    declared = set(COMPOSE["volumes"])
    for name, spec in SERVICES.items():
        for mount in spec.get("volumes", []):
            source = mount_parts(mount)[0]
            default = re.fullmatch(r"\$\{[A-Z_]+:-(\./[^}]+)\}", source)
            if default is not None:  # a configuration file of the repository, read-only
                assert (ROOT / default.group(1)).is_file() and mount.endswith(":ro"), mount
                continue
            assert source in declared, f"{name}: {source} is not a named volume"


def test_workers_see_the_eeg_services_folder_where_they_look_for_it() -> None:
    """A live session's worker installs the classifier into, and stores the recording from,
    ``<its BGRL_DATA_DIR>/eeg``: the EEG service's own folder (EEGSettings.eeg_dir)."""
    eeg_dir = EEGSettings(data_dir=Path(OURS["eeg"]["environment"]["BGRL_DATA_DIR"])).eeg_dir
    worker_dir = EEGSettings(data_dir=Path(OURS["worker"]["environment"]["BGRL_DATA_DIR"])).eeg_dir
    eeg = {mount_parts(m)[1]: mount_parts(m)[0] for m in OURS["eeg"]["volumes"]}
    worker = {mount_parts(m)[1]: mount_parts(m)[0] for m in OURS["worker"]["volumes"]}
    assert eeg[str(eeg_dir)] == worker[str(worker_dir)] == "eegdata"


def test_the_eeg_service_finds_lsl_streams_through_known_peers() -> None:
    eeg = OURS["eeg"]
    target = eeg["environment"]["LSLAPICFG"]
    (mount,) = [m for m in eeg["volumes"] if mount_parts(m)[1] == target]
    path = re.fullmatch(r"\$\{BGRL_LSL_CONFIG:-(\./[^}]+)\}", mount_parts(mount)[0])
    assert path is not None, mount
    config = configparser.ConfigParser()
    config.read(ROOT / path.group(1))
    assert config["lab"]["KnownPeers"].startswith("{")


def test_dockerfile_runs_the_platform_with_settings_it_knows() -> None:
    dockerfile = (ROOT / "Dockerfile").read_text()
    client, *services = [yaml.safe_load(c) for c in re.findall(r"^CMD (\[.*\])$", dockerfile, re.M)]
    assert client == ["--help"] and 'ENTRYPOINT ["bgrl"]' in dockerfile  # the client image
    assert len(services) == 2
    for argv in services:
        check_entry_point(argv)
    stages = re.findall(r"^FROM \S+ AS (\S+)$", dockerfile, re.MULTILINE)
    assert stages == ["base", "client", "api", "platform"]  # platform: the default target
    assert {spec["build"]["target"] for spec in OURS.values()} <= set(stages)
    installs = re.findall(r"pip install (.*?)'\.\[(\w+)\]'", dockerfile, re.DOTALL)
    assert [extra for _, extra in installs] == ["client", "api", "worker"]
    assert all("-c requirements.lock" in options for options, _ in installs)
    exposed = set(re.findall(r"^EXPOSE (.*)$", dockerfile, re.MULTILINE)[-1].split())
    assert exposed == {OURS[s]["environment"][v] for s, v in PORT_VARIABLES.items()}
    variables = set(re.findall(r"\b(BGRL_[A-Z_]+)=", dockerfile))
    assert variables == {"BGRL_DATA_DIR", "BGRL_ARTIFACT_DIR"}
    assert variables <= env_names(WorkerSettings) & env_names(ApiSettings)
    assert "torch==" not in dockerfile  # the version comes from pyproject.toml
