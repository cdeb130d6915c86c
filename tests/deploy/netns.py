"""A lab of Linux network namespaces: one "host" a namespace, wired to a switch (a bridge in
a namespace of its own: no address or route on the machine itself), each with its compose
hostnames in ``/etc/netns/<namespace>/hosts``; processes started in a host by
``ip netns exec``; code of this test run inside a host from a thread that entered its
namespace (``setns`` changes only the calling thread's namespace)."""

from __future__ import annotations

import contextlib
import ctypes
import os
import shutil
import signal
import subprocess
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

import psutil

T = TypeVar("T")
CLONE_NEWNET = 0x40000000
SUBNET = "10.231.77"
"""A private /24 used only inside the test's namespaces."""


def netns_unavailable() -> str | None:
    """Why namespaces cannot be made here, or None."""
    if os.geteuid() != 0:
        return "needs root (ip netns add)"
    if shutil.which("ip") is None:
        return "needs the ip command (iproute2)"
    probe = f"bgrl-probe-{os.getpid()}"
    done = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if done.returncode != 0:
        return f"ip netns is not permitted here ({done.stderr.strip()})"
    subprocess.run(["ip", "netns", "del", probe], check=False)
    return None


def ip(*args: str, netns: str | None = None) -> None:
    cmd = ["ip", *(["-n", netns] if netns else []), *args]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)}: {done.stderr.strip()}")


def descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (children in their own sessions included)."""
    try:
        return [child.pid for child in psutil.Process(pid).children(recursive=True)]
    except psutil.NoSuchProcess:
        return []


class Lab:
    """Hosts on one switch. ``add_host(name)`` -> its address; ``close()`` removes all."""

    def __init__(self, tag: str) -> None:
        self.tag = tag
        self.switch = f"{tag}-switch"
        self.hosts: dict[str, str] = {}
        self.procs: list[subprocess.Popen[bytes]] = []
        self.aliases: dict[str, list[str]] = {}
        ip("netns", "add", self.switch)
        ip("link", "add", "br0", "type", "bridge", netns=self.switch)
        ip("link", "set", "br0", "up", netns=self.switch)

    def namespace(self, host: str) -> str:
        return f"{self.tag}-{host}"

    def add_host(self, host: str, aliases: list[str] | None = None) -> str:
        """A namespace ``host`` with ``lo`` and ``eth0`` up on the switch; its address."""
        index = len(self.hosts) + 2
        address = f"{SUBNET}.{index}"
        ns = self.namespace(host)
        ip("netns", "add", ns)
        port = f"p{index}"  # the switch side of the cable
        ip("link", "add", port, "netns", self.switch, "type", "veth", "peer", "name", "eth0",
           "netns", ns)  # fmt: skip
        ip("link", "set", port, "master", "br0", netns=self.switch)
        ip("link", "set", port, "up", netns=self.switch)
        ip("link", "set", "lo", "up", netns=ns)
        ip("addr", "add", f"{address}/24", "dev", "eth0", netns=ns)
        ip("link", "set", "eth0", "up", netns=ns)
        self.hosts[host] = address
        self.aliases[host] = [host, *(aliases or [])]
        self.write_hosts_files()
        return address

    def write_hosts_files(self) -> None:
        """``/etc/netns/<ns>/hosts`` of every host: localhost and every host's names."""
        lines = ["127.0.0.1 localhost"]
        lines += [f"{self.hosts[h]} {' '.join(self.aliases[h])}" for h in self.hosts]
        for host in self.hosts:
            folder = Path("/etc/netns") / self.namespace(host)
            folder.mkdir(parents=True, exist_ok=True)
            (folder / "hosts").write_text("\n".join(lines) + "\n")

    def cable(self, host: str, up: bool) -> None:
        """Plug or pull ``host``'s cable (its port on the switch)."""
        index = list(self.hosts).index(host) + 2
        ip("link", "set", f"p{index}", "up" if up else "down", netns=self.switch)

    def start(
        self, host: str, argv: list[str], *, env: dict[str, str], log: Path, cwd: Path,
        user: str | None = None,
    ) -> subprocess.Popen[bytes]:  # fmt: skip
        """``argv`` with exactly ``env`` in ``host``'s namespace (its own process group)."""
        prefix = ["ip", "netns", "exec", self.namespace(host)]
        if user is not None:
            prefix += ["runuser", "-u", user, "--"]
        proc = subprocess.Popen(
            [*prefix, *argv], env=env, cwd=cwd, stdout=log.open("ab"),
            stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
        self.procs.append(proc)
        return proc

    def run(self, host: str, argv: list[str], env: dict[str, str] | None = None,
            timeout: float = 30.0) -> subprocess.CompletedProcess[str]:  # fmt: skip
        return subprocess.run(
            ["ip", "netns", "exec", self.namespace(host), *argv],
            env=env, capture_output=True, text=True, timeout=timeout,
        )  # fmt: skip

    @contextlib.contextmanager
    def inside(self, host: str) -> Iterator[Callable[[Callable[[], T]], T]]:
        """A function running a callable in a thread inside ``host``'s network namespace
        (sockets it opens belong to that namespace)."""
        path = f"/run/netns/{self.namespace(host)}"

        def enter() -> None:
            libc = ctypes.CDLL("libc.so.6", use_errno=True)
            with open(path) as fh:
                if libc.setns(fh.fileno(), CLONE_NEWNET) != 0:
                    raise OSError(ctypes.get_errno(), f"setns {path}")

        with ThreadPoolExecutor(max_workers=1, initializer=enter) as pool:
            yield lambda fn: pool.submit(fn).result()

    def stop(self, proc: subprocess.Popen[bytes], sig: int = signal.SIGTERM,
             timeout: float = 15.0) -> None:  # fmt: skip
        """Signal ``proc``'s process group (SIGKILL: and every process below it, in their own
        sessions too); SIGKILL it if it has not exited in time."""
        if sig == signal.SIGKILL:
            for pid in descendants(proc.pid):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
        if proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, sig)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()

    def close(self) -> None:
        """Stop every process, then remove the namespaces and their hosts files."""
        for proc in reversed(self.procs):
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGTERM)
        for proc in reversed(self.procs):
            self.stop(proc, timeout=10)
        for host in self.hosts:
            subprocess.run(["ip", "netns", "del", self.namespace(host)], check=False)
            shutil.rmtree(Path("/etc/netns") / self.namespace(host), ignore_errors=True)
        subprocess.run(["ip", "netns", "del", self.switch], check=False)
