"""The supervisor of ``bgrl up`` on small stand-in processes: restarts with backoff, a crash
loop stops one process (or everything for an essential one), a hung service is restarted,
the state reaches the status file, and a child dies with a SIGKILLed parent."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

from services.cli.ports import PortError, bind_all
from services.cli.supervisor import ProcessSpec, Supervisor, SupervisorSettings
from tests.helpers import free_port

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs Linux")

supervisor_ready: list[list[str]] = []
"""What the supervisor under test announced once ready (its ``on_ready`` calls)."""
SLEEPER = [sys.executable, "-c", "import time; time.sleep(120)"]
CRASHER = [sys.executable, "-c", "raise SystemExit(3)"]


def spec(name: str, cmd: list[str], **fields: object) -> ProcessSpec:
    return ProcessSpec(name, fields.pop("kind", name), cmd, dict(os.environ), **fields)  # type: ignore[arg-type]


def wait_for(condition: Callable[[], bool], what: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting: {what}"
        time.sleep(0.05)


@contextmanager
def supervising(
    specs: list[ProcessSpec], tmp_path: Path, **settings: float
) -> Iterator[tuple[Supervisor, list[str], dict[str, int]]]:
    """A supervisor of ``specs`` running in a thread; yields it, its output lines and
    ``{"code": run's return}`` once it returned."""
    lines: list[str] = []
    supervisor_ready.clear()
    supervisor = Supervisor(
        specs,
        SupervisorSettings(**settings),
        status_file=tmp_path / "processes.json",
        echo=lines.append,
    )
    stop = threading.Event()
    returned: dict[str, int] = {}
    supervisor.start()
    thread = threading.Thread(
        target=lambda: returned.setdefault("code", supervisor.run(stop, supervisor_ready.append))
    )
    thread.start()
    try:
        yield supervisor, lines, returned
    finally:
        stop.set()
        thread.join(timeout=30)
        supervisor.stop()


def status(tmp_path: Path) -> dict[str, dict[str, object]]:
    return json.loads((tmp_path / "processes.json").read_text())["processes"]


def test_a_crash_loop_stops_that_process_and_the_rest_stay_up(tmp_path: Path) -> None:
    never = f"http://127.0.0.1:{free_port()}/health"  # the sim never gets to answer
    specs = [spec("sim", CRASHER, health_url=never), spec("worker-1", SLEEPER, kind="worker")]
    with supervising(specs, tmp_path, restart_limit=3, restart_window_s=60) as (sup, lines, _):
        crasher, sleeper = sup.processes
        wait_for(lambda: crasher.state == "stopped", "the crash loop to be stopped")
        assert crasher.restarts == 2  # started, restarted twice, the third exit gives up
        assert sleeper.alive() and sleeper.restarts == 0
        assert lines[0] == "sim exited with code 3; restarting it in 1 s (restart 1)"
        assert lines[1] == "sim exited with code 3; restarting it in 2 s (restart 2)"
        assert lines[2] == (
            "sim: crash loop: 3 exits in 60 s (last: code 3); stopped, the other processes stay up"
        )
        wait_for(lambda: status(tmp_path)["sim"]["state"] == "stopped", "the status file")
        written = status(tmp_path)
        assert written["sim"]["reason"] == "crash loop: 3 exits in 60 s (last: code 3)"
        assert written["sim"]["restarts"] == 2
        assert written["worker-1"]["state"] == "running"
        assert written["worker-1"]["pid"] == sleeper.proc.pid  # type: ignore[union-attr]
        # ready once nothing restarts any more, naming what is not running
        wait_for(lambda: bool(supervisor_ready), "the start-up announcement")
        assert supervisor_ready == [["sim (crash loop: 3 exits in 60 s (last: code 3))"]]
    assert not sleeper.alive()  # stop() ended it


def test_a_killed_process_is_restarted_and_counted(tmp_path: Path) -> None:
    with supervising([spec("learner", SLEEPER)], tmp_path) as (sup, lines, _):
        (process,) = sup.processes
        first = process.proc.pid  # type: ignore[union-attr]
        os.kill(first, signal.SIGKILL)
        wait_for(lambda: process.restarts == 1 and process.alive(), "the restart")
        assert process.proc.pid != first  # type: ignore[union-attr]
        assert lines == ["learner exited with code -9 (SIGKILL); restarting it in 1 s (restart 1)"]
        wait_for(lambda: status(tmp_path)["learner"]["restarts"] == 1, "the status file")
        assert status(tmp_path)["learner"]["last_exit"] == "code -9 (SIGKILL)"


def test_an_essential_crash_loop_stops_everything(tmp_path: Path) -> None:
    specs = [spec("api", CRASHER, essential=True), spec("sim", SLEEPER)]
    with supervising(specs, tmp_path, restart_limit=2) as (sup, lines, returned):
        wait_for(lambda: "code" in returned, "run to return")
        assert returned["code"] == 1
        assert sup.fatal == (
            "api: crash loop: 2 exits in 60 s (last: code 3); stopping everything (nothing "
            "works without the api)"
        )
        assert lines[-1] == sup.fatal


def test_a_service_that_stops_answering_is_restarted(tmp_path: Path) -> None:
    port = free_port()
    server = [sys.executable, "-m", "http.server", str(port), "--bind", "127.0.0.1"]
    health = f"http://127.0.0.1:{port}/"
    settings = {"health_interval_s": 0.2, "health_timeout_s": 1.5, "start_timeout_s": 30}
    with supervising([spec("eeg", server, health_url=health)], tmp_path, **settings) as (
        sup,
        lines,
        _,
    ):
        (process,) = sup.processes
        wait_for(lambda: process.state == "running", "the first health check")
        hung = process.proc.pid  # type: ignore[union-attr]
        os.kill(hung, signal.SIGSTOP)  # alive, but answers nothing
        wait_for(lambda: process.restarts == 1 and process.state == "running", "the restart")
        assert lines[0] == f"eeg: no answer from {health} for 1.5 s; stopping it"
        assert lines[1].startswith(f"eeg exited with no answer from {health} for 1.5 s;")
        assert process.proc.pid != hung  # type: ignore[union-attr]


def test_a_hung_process_among_two_sharing_a_port_is_killed_and_restarted(
    tmp_path: Path,
) -> None:
    """Two HTTP processes serve one socket (as the api's do): a health check through the
    port reaches either, so each beats into its own file. SIGSTOP of one: the other answers
    every request meanwhile, and the stopped one is killed once its heartbeat is older than
    ``heartbeat_timeout_s`` and restarted (documented: within that time plus its start)."""
    timeout_s = 3.0
    with socket.create_server(("127.0.0.1", 0)) as shared:
        url = f"http://127.0.0.1:{shared.getsockname()[1]}/"
        fd = shared.fileno()
        child = [sys.executable, "-m", "services.cli.child", "tests.worker.pid_app:app"]
        specs = [
            spec(
                name, [*child, "--fd", str(fd), "--heartbeat", str(tmp_path / f"{name}.beat")],
                kind="api", pass_fds=(fd,), heartbeat_file=tmp_path / f"{name}.beat",
            )
            for name in ("api-1", "api-2")
        ]  # fmt: skip
        with supervising(specs, tmp_path, heartbeat_timeout_s=timeout_s) as (sup, lines, _):
            hung, sibling = sup.processes
            wait_for(lambda: all(p.state == "running" for p in sup.processes), "both serving")
            hung_pid = hung.proc.pid  # type: ignore[union-attr]
            os.kill(hung_pid, signal.SIGSTOP)
            stopped_at = time.monotonic()
            answered_by = set()
            while not (hung.restarts == 1 and hung.state == "running"):
                assert time.monotonic() - stopped_at < 60, "the hung process was not restarted"
                answered_by.add(httpx.get(url, timeout=5).json()["pid"])  # a new connection
                time.sleep(0.1)
            took = time.monotonic() - stopped_at
            assert hung_pid not in answered_by  # it answered nothing while stopped
            assert not process_alive(hung_pid)
            assert lines[0].startswith("api-1: no heartbeat for ")
            assert lines[0].endswith(" s (its event loop does not run); killing it")
            age = float(lines[0].split("no heartbeat for ")[1].split(" s")[0])
            assert timeout_s <= age <= timeout_s + 1.5  # noticed within a second or so
            assert sibling.restarts == 0 and sibling.proc.pid in answered_by  # type: ignore[union-attr]
            assert httpx.get(url, timeout=5).status_code == 200
            assert status(tmp_path)["api-1"]["last_exit"].startswith("no heartbeat for ")
    print(f"hung process restarted {took:.1f} s after its SIGSTOP (timeout {timeout_s} s)")


def test_ports_are_checked_before_anything_starts(tmp_path: Path) -> None:
    held = socket.socket()
    held.bind(("127.0.0.1", 0))
    held.listen()
    port = held.getsockname()[1]
    free = free_port()
    try:
        with pytest.raises(PortError) as refused:
            bind_all([("BGRL_PORT", "127.0.0.1", free), ("BGRL_SIM_PORT", "127.0.0.1", port)])
        assert str(refused.value).startswith(
            f"BGRL_SIM_PORT={port}: 127.0.0.1:{port} is in use by pid {os.getpid()} ("
        )
        assert "\n" not in str(refused.value)
        # the port bound before the refusal was given back
        bind_all([("BGRL_PORT", "127.0.0.1", free)])[0].close()
        with pytest.raises(PortError, match=f"BGRL_EEG_PORT={free}: the same port as BGRL_PORT"):
            bind_all([("BGRL_PORT", "127.0.0.1", free), ("BGRL_EEG_PORT", "127.0.0.1", free)])
    finally:
        held.close()


def test_a_child_dies_with_its_parent_killed_by_sigkill(tmp_path: Path) -> None:
    """A parent that starts a child as the supervisor does, then is SIGKILLed: the child,
    adopted by init, gets its parent-death signal."""
    pid_file = tmp_path / "child.pid"
    parent = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from services.cli.supervisor import spawn_child; "
            f"child = spawn_child({SLEEPER!r}); open(sys.argv[1], 'w').write(str(child.pid)); "
            "time.sleep(120)",
            str(pid_file),
        ]
    )
    try:
        wait_for(lambda: pid_file.exists() and pid_file.read_text() != "", "the child")
        child = int(pid_file.read_text())
        assert process_alive(child)
        parent.kill()
        parent.wait()
        wait_for(lambda: not process_alive(child), "the orphan to die", timeout_s=10)
    finally:
        if parent.poll() is None:
            parent.kill()


def process_alive(pid: int) -> bool:
    """True if ``pid`` runs and is no zombie."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"
