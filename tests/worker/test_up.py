"""``bgrl up``: bad settings and ports in use stop it before anything starts; every process
finds the others at the ports it started (not the defaults); it serves, restarts what dies,
a SIGKILL of it leaves nothing behind, and SIGTERM stops every process within 10 s."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from datetime import timedelta
from pathlib import Path
from unittest import mock

import httpx
import psutil
import pytest

from services.api.settings import ApiSettings
from services.cli.serve import internal_urls
from services.sim.settings import SimSettings
from services.worker.live_services import LiveSettings
from tests.helpers import env_without_bgrl, free_port

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs Linux")


def port_free(port: int) -> bool:
    """Nothing listens on ``port`` (Linux refuses SO_REUSEADDR's bind only to a listener;
    without it, a closed connection in TIME_WAIT would count)."""
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True


def children(pid: int, *, recursive: bool = False) -> dict[int, str]:
    """Live (not zombie) processes below ``pid``, its children only unless ``recursive``:
    pid -> command line."""
    found = {}
    for child in psutil.Process(pid).children(recursive=recursive):
        try:
            if child.status() != psutil.STATUS_ZOMBIE:
                found[child.pid] = " ".join(child.cmdline())
        except psutil.NoSuchProcess:
            continue
    return found


def alive(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def environ(pid: int) -> dict[str, str]:
    """The environment a process was started with."""
    return psutil.Process(pid).environ()


def wait_until(condition: object, what: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():  # type: ignore[operator]
        assert time.monotonic() < deadline, f"timed out: {what}"
        time.sleep(0.2)


def bgrl_up(tmp_path: Path, *args: str, **env: str) -> subprocess.Popen[bytes]:
    """``bgrl up`` in ``tmp_path`` with only ``env`` as settings; output in out.log/err.log
    (files, not pipes: a full pipe would block the services writing their logs)."""
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli.main", "up", *args],
        cwd=tmp_path,
        env={**env_without_bgrl(), **env},
        stdout=(tmp_path / "out.log").open("wb"),
        stderr=(tmp_path / "err.log").open("wb"),
    )


@pytest.mark.parametrize(
    ("variable", "value"), [("BGRL_SIM_PORT", "abc"), ("BGRL_EEG_PORT", "70000")]
)
def test_bad_setting_is_one_line_before_listening(
    tmp_path: Path, variable: str, value: str
) -> None:
    proc = bgrl_up(tmp_path, **{variable: value})
    assert proc.wait(timeout=120) == 2
    out, err = (tmp_path / "out.log").read_text(), (tmp_path / "err.log").read_text()
    assert err.strip().count("\n") == 0
    assert err.startswith(f"error: invalid setting: {variable} (got ")
    assert "http://" not in out
    assert not (tmp_path / "data").exists()  # nothing was created either


def test_a_port_in_use_is_one_line_naming_the_variable_and_holder(tmp_path: Path) -> None:
    held = socket.socket()
    held.bind(("127.0.0.1", 0))
    held.listen()
    port = held.getsockname()[1]
    try:
        proc = bgrl_up(tmp_path, BGRL_PORT=str(free_port()), BGRL_EEG_PORT=str(port))
        assert proc.wait(timeout=120) == 2
    finally:
        held.close()
    err = (tmp_path / "err.log").read_text()
    assert err.count("\n") == 1
    assert err.startswith(
        f"error: BGRL_EEG_PORT={port}: 127.0.0.1:{port} is in use by pid {os.getpid()} ("
    )
    assert "http://" not in (tmp_path / "out.log").read_text()
    assert not (tmp_path / "data").exists()


def test_internal_urls_come_from_the_ports_unless_given() -> None:
    """The api and the workers call the sim, EEG and learner services where they listen."""
    with mock.patch.dict(
        os.environ,
        {"BGRL_SIM_PORT": "9101", "BGRL_SIM_HOST": "0.0.0.0", "BGRL_LEARNER_URL": "http://l:1"},
    ):
        settings = {"sim": SimSettings()}
        urls = internal_urls(settings, os.environ)
    assert urls == {"BGRL_SIM_URL": "http://127.0.0.1:9101", "BGRL_LEARNER_URL": "http://l:1"}


def up_ports() -> dict[str, int]:
    return {"api": free_port(), "sim": free_port(), "eeg": free_port(), "learner": free_port()}


def port_env(ports: dict[str, int]) -> dict[str, str]:
    return {
        "BGRL_PORT": str(ports["api"]),
        "BGRL_SIM_PORT": str(ports["sim"]),
        "BGRL_EEG_PORT": str(ports["eeg"]),
        "BGRL_LEARNER_PORT": str(ports["learner"]),
    }


def wait_up(proc: subprocess.Popen[bytes], tmp_path: Path) -> str:
    """The start-up block, once printed."""
    out = tmp_path / "out.log"

    def printed() -> bool:
        assert proc.poll() is None, (tmp_path / "err.log").read_text()[-3000:]
        return "Ctrl-C stops everything." in out.read_text()

    wait_until(printed, "the start-up block", timeout_s=180)
    return out.read_text()


@pytest.mark.slow
def test_up_wires_serves_restarts_and_a_sigkill_of_it_leaves_nothing(tmp_path: Path) -> None:
    """The whole platform with two api processes: every process calls the others at the
    ports started; a killed worker and a killed api process are restarted and counted; the
    start-up ends with one block; a SIGKILL of ``bgrl up`` ends every kind of process (api,
    sim, EEG, learner, worker) and frees every port."""
    ports = up_ports()
    proc = bgrl_up(tmp_path, **port_env(ports), BGRL_API_WORKERS="2", BGRL_WORKERS="1")
    try:
        out = wait_up(proc, tmp_path)
        # one door: the internal services answer only calls with the kept service token
        token = (tmp_path / "data" / "service-token").read_text().strip()
        assert oct((tmp_path / "data" / "service-token").stat().st_mode & 0o777) == "0o600"
        maps = f"http://127.0.0.1:{ports['sim']}/maps"
        assert httpx.get(maps, timeout=10).status_code == 401
        assert httpx.get(maps, headers={"X-Service-Token": token}, timeout=10).status_code == 200
        # the api and the worker call the services at the ports started, not 8001-8003
        spawned = children(proc.pid)
        api = next(pid for pid, cmd in spawned.items() if "services.api.app:app" in cmd)
        workers = [pid for pid, cmd in spawned.items() if " worker " in cmd]
        with mock.patch.dict(os.environ, environ(api), clear=True):
            api_settings = ApiSettings()
        with mock.patch.dict(os.environ, environ(workers[0]), clear=True):
            worker_settings = LiveSettings()
        assert api_settings.sim_url == f"http://127.0.0.1:{ports['sim']}"
        assert api_settings.eeg_url == f"http://127.0.0.1:{ports['eeg']}"
        assert worker_settings.sim_url == f"http://127.0.0.1:{ports['sim']}"
        assert worker_settings.eeg_url == f"http://127.0.0.1:{ports['eeg']}"
        assert worker_settings.learner_url == f"http://127.0.0.1:{ports['learner']}"
        # a killed worker and a killed api process come back, counted in /readyz
        readyz = f"http://127.0.0.1:{ports['api']}/readyz"
        first = httpx.get(readyz, timeout=10).json()["processes"]
        assert {p["kind"] for p in first.values()} == {"api", "sim", "eeg", "learner", "worker"}
        assert first["worker-1"]["pid"] == workers[0]
        os.kill(workers[0], signal.SIGKILL)
        os.kill(first["api-1"]["pid"], signal.SIGKILL)  # api-2 answers meanwhile

        def back(name: str) -> bool:
            now = httpx.get(readyz, timeout=10).json()["processes"][name]
            return bool(now["restarts"] == 1 and now["state"] == "running")

        wait_until(lambda: back("api-1") and back("worker-1"), "api-1 and worker-1 restarted")
        ready = httpx.get(readyz, timeout=10)
        assert ready.status_code == 200 and ready.json()["status"] == "ready"
        assert ready.json()["processes"]["worker-1"]["last_exit"] == "code -9 (SIGKILL)"
        tree = children(proc.pid, recursive=True)
        kinds = " ".join(tree.values())
        for app in ("services.api.app", "services.sim.app", "services.eeg.service.app", "learner"):
            assert app in kinds
        assert len(tree) == 6, tree  # two api processes, sim, eeg, learner, one worker
        proc.kill()
        proc.wait()
        wait_until(lambda: not [p for p in tree if alive(p)], "every process to die", 20)
        wait_until(lambda: all(port_free(port) for port in ports.values()), "free ports", 20)
    finally:
        if proc.poll() is None:
            proc.kill()
    data = (tmp_path / "data").resolve()
    block = out[out.index("-" * 72) :]  # the start-up ends with one block
    assert block.startswith("-" * 72 + "\nbgrl is up\n")
    assert f"  dashboard    http://127.0.0.1:{ports['api']}/ " in block
    assert "  admin        admin@localhost\n" in block
    assert f"  password     in {data / 'first-admin-password'} " in block
    assert f"  data folder  {data}\n" in block
    assert f"BGRL_EEG_URL=http://127.0.0.1:{ports['eeg']}" in block
    assert oct((data / "first-admin-password").stat().st_mode & 0o777) == "0o600"
    err = (tmp_path / "err.log").read_text()
    assert "worker-1 exited with code -9 (SIGKILL); restarting it in 1 s (restart 1)" in err
    assert (data / "bgrl.db").is_file()  # the data stays for the next start


def test_up_settles_a_dead_workers_job_with_no_worker_and_sigterm_stops_it(
    tmp_path: Path,
) -> None:
    """The reaper runs in ``bgrl up`` itself: a job whose worker died (here: before this
    start) is failed with the reason on its last attempt, though no worker runs. SIGTERM
    then stops every process within 10 s and frees the ports."""
    from services.core.db import jobs as job_rows
    from services.core.db.base import utcnow
    from services.core.db.migrate import upgrade_database
    from services.core.db.models import Job
    from services.core.db.session import make_engine, make_session_factory

    data = tmp_path / "data"
    data.mkdir()
    url = f"sqlite:///{data / 'bgrl.db'}"
    upgrade_database(url)
    engine = make_engine(url)
    sessions = make_session_factory(engine)
    with sessions() as session:
        job = Job(kind="guided_ppo", config={}, max_attempts=1)
        session.add(job)
        session.commit()
        job_id = job.id
        job_rows.claim_job(session, job_id, "gone-worker", 30)
        session.get(Job, job_id).lease_expires_at = utcnow() - timedelta(seconds=1)  # type: ignore[union-attr]
        session.commit()
    ports = {"api": free_port(), "sim": free_port()}
    proc = bgrl_up(
        tmp_path,
        "--only",
        "api",
        "--only",
        "sim",
        BGRL_PORT=str(ports["api"]),
        BGRL_SIM_PORT=str(ports["sim"]),
    )
    try:
        wait_up(proc, tmp_path)

        def settled() -> bool:
            with sessions() as session:
                return session.get(Job, job_id).status == "failed"  # type: ignore[union-attr]

        wait_until(settled, "the reaper in bgrl up")
        with sessions() as session:
            assert session.get(Job, job_id).error == "worker lost on the last of 1 attempts"  # type: ignore[union-attr]
        spawned = set(children(proc.pid))
        assert len(spawned) == 2  # the api and the sim
        asked = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
        took = time.monotonic() - asked
    finally:
        if proc.poll() is None:
            proc.kill()
        engine.dispose()
    assert took < 10.0, f"stopping took {took:.1f} s"
    assert [pid for pid in spawned if alive(pid)] == []
    assert all(port_free(port) for port in ports.values())
    assert "stopped" in (tmp_path / "out.log").read_text()
    status = json.loads((data / "run" / "processes.json").read_text())
    assert list(status["processes"]) == ["api", "sim"]
