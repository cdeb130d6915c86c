"""``bgrl up``: bad settings stop it before it claims to listen; it serves, restarts a worker
that dies, and SIGTERM stops every process within 10 s and frees the ports."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from tests.helpers import env_without_bgrl, free_port, wait_healthy

pytestmark = pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs Linux /proc")


def port_free(port: int) -> bool:
    with socket.socket() as sock:
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True


def children(pid: int) -> dict[int, str]:
    """Live child processes of ``pid``: pid -> command line."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        state = stat.rsplit(")", 1)[1].split()[0]
        if ppid == pid and state != "Z":
            found[int(entry.name)] = cmdline
    return found


def alive(pid: int) -> bool:
    try:
        state = (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def bgrl_up(tmp_path: Path, **env: str) -> subprocess.Popen[bytes]:
    """``bgrl up`` in ``tmp_path`` with only ``env`` as settings; output in out.log/err.log
    (files, not pipes: a full pipe would block the services writing their logs)."""
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli.main", "up"],
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


@pytest.mark.slow
def test_up_serves_restarts_a_dead_worker_and_sigterm_stops_everything(tmp_path: Path) -> None:
    ports = {"api": free_port(), "sim": free_port(), "eeg": free_port(), "learner": free_port()}
    proc = bgrl_up(
        tmp_path,
        BGRL_PORT=str(ports["api"]),
        BGRL_SIM_PORT=str(ports["sim"]),
        BGRL_EEG_PORT=str(ports["eeg"]),
        BGRL_LEARNER_PORT=str(ports["learner"]),
        BGRL_SIM_HOST="127.0.0.1",
        BGRL_WORKERS="1",
    )
    try:
        for port in ports.values():
            wait_healthy(f"http://127.0.0.1:{port}", proc, tmp_path / "err.log")
        # one door: the internal services answer only calls with the kept service token
        token = (tmp_path / "data" / "service-token").read_text().strip()
        assert oct((tmp_path / "data" / "service-token").stat().st_mode & 0o777) == "0o600"
        maps = f"http://127.0.0.1:{ports['sim']}/maps"
        assert httpx.get(maps, timeout=10).status_code == 401
        assert httpx.get(maps, headers={"X-Service-Token": token}, timeout=10).status_code == 200
        workers = [pid for pid, cmd in children(proc.pid).items() if " worker " in cmd]
        assert len(workers) == 1
        os.kill(workers[0], signal.SIGKILL)
        deadline = time.monotonic() + 30
        while True:
            replaced = [p for p, cmd in children(proc.pid).items() if " worker " in cmd]
            if replaced and replaced != workers:
                break
            assert time.monotonic() < deadline, "the dead worker was not restarted"
            time.sleep(0.2)
        spawned = set(children(proc.pid))
        assert len(spawned) == 5  # api, sim, eeg, learner, one worker
        asked = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
        took = time.monotonic() - asked
        out = (tmp_path / "out.log").read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert took < 10.0, f"stopping took {took:.1f} s"
    for name in ("api", "sim", "eeg", "learner"):
        assert f"http://127.0.0.1:{ports[name]}  (docs: http://127.0.0.1:{ports[name]}/docs" in out
    assert "worker-1 exited with code -9; restarting it" in (tmp_path / "err.log").read_text()
    assert [pid for pid in spawned if alive(pid)] == []
    assert all(port_free(port) for port in ports.values())
    assert (tmp_path / "data" / "bgrl.db").is_file()  # the data stays for the next start
