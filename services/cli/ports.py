"""The listening sockets of ``bgrl up``, bound before any process starts.

``bgrl up`` binds every service's port itself and hands the socket to the service's
processes (``services.cli.child``): a port in use is found before anything starts, as one
line naming the variable and the process that holds it, and a restarted service finds its
port still held (connections wait in the queue instead of being refused).
"""

from __future__ import annotations

import contextlib
import errno
import socket

import psutil

BACKLOG = 2048
"""Connections the kernel queues per port (uvicorn's default)."""


class PortError(RuntimeError):
    """A port cannot be bound; the message is one line naming the variable."""


def port_holder(port: int) -> str | None:
    """``pid N (command line)`` of the process listening on TCP ``port``, if visible to this
    user (``/proc/net/tcp`` and ``/proc/*/fd``, read by psutil), else None."""
    try:
        connections = psutil.net_connections(kind="tcp")
    except (psutil.Error, OSError):
        return None
    for conn in connections:
        if conn.status != psutil.CONN_LISTEN or not conn.laddr or conn.laddr.port != port:
            continue
        if conn.pid is None:
            return None
        try:
            command = " ".join(psutil.Process(conn.pid).cmdline())
        except psutil.Error:
            command = "?"
        if len(command) > 100:
            command = command[:97] + "..."
        return f"pid {conn.pid} ({command})"
    return None


def listening_socket(variable: str, host: str, port: int) -> socket.socket:
    """A TCP socket bound to ``host:port`` and listening; :class:`PortError` otherwise.

    ``variable`` names the setting the port comes from (e.g. ``BGRL_SIM_PORT``).
    """
    try:
        family, kind, proto, _, address = socket.getaddrinfo(
            host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )[0]
    except socket.gaierror as exc:
        raise PortError(f"{variable}: cannot resolve the host {host!r} ({exc.strerror})") from None
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(BACKLOG)
    except OSError as exc:
        sock.close()
        where = f"{host}:{port}"
        if isinstance(exc, PermissionError):
            raise PortError(f"{variable}={port}: not allowed to listen on {where}") from None
        holder = port_holder(port)
        if exc.errno == errno.EADDRINUSE and holder is None:
            holder = "another process (not visible to this user)"
        if holder is not None:
            raise PortError(
                f"{variable}={port}: {where} is in use by {holder}; stop it or choose another port"
            ) from None
        raise PortError(f"{variable}={port}: cannot listen on {where}: {exc.strerror}") from None
    return sock


def bind_all(wanted: list[tuple[str, str, int]]) -> list[socket.socket]:
    """Bind every ``(variable, host, port)`` or none: :class:`PortError` for the first port
    that cannot be bound (the ones bound so far are closed), also when two variables name
    the same port."""
    seen: dict[int, str] = {}
    for variable, _, port in wanted:
        if port in seen:
            raise PortError(f"{variable}={port}: the same port as {seen[port]}; give each its own")
        seen[port] = variable
    sockets: list[socket.socket] = []
    try:
        for variable, host, port in wanted:
            sockets.append(listening_socket(variable, host, port))
    except PortError:
        for sock in sockets:
            with contextlib.suppress(OSError):
                sock.close()
        raise
    return sockets
