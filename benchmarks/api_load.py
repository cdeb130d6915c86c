"""The read-load generator of ``bgrl bench api``: a separate, light process (asyncio only).

``python -m benchmarks.api_load --url URL --bare-url BARE --rate 200 --duration 30 --blocks
6`` reads a bearer token from stdin, then sends ``GET /api/v1/jobs?limit=50`` to the api
(``list``) and to the bare app of the same answer (``bare``, :mod:`benchmarks.api_bare`) in
alternating blocks, ``rate`` requests/s each, open loop: every request leaves at its
scheduled time whatever the earlier ones are doing, and its latency runs from that
scheduled time to the end of the response, so a server (or this client) falling behind
shows up in the figures. Prints a JSON summary per route.

With ``--watch-pids`` (the api's and the bare app's processes) it also samples, at the
start and end of every block, the CPU time those processes used (psutil), its own, and the
whole machine's, so each server gets its CPU per request under the load: what it spent, what
the generator spent, and how busy the cores were (the database server and everyone else).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import statistics
import sys
import time
from typing import Any
from urllib.parse import urlsplit

import psutil

JOBS_ROUTE = "/api/v1/jobs?limit=50"
LIST = "list"
"""The figures of ``JOBS_ROUTE`` on the api."""
BARE = "bare"
"""The figures of ``JOBS_ROUTE`` on the bare app answering the same bytes."""


def percentile(sorted_values: list[float], q: float) -> float:
    """Nearest-rank percentile ``q`` (0..100) of already sorted values."""
    rank = max(1, math.ceil(q / 100 * len(sorted_values)))
    return sorted_values[rank - 1]


def latency_summary(latencies_ms: list[float]) -> dict[str, float | int]:
    """Count, p50, p99, mean and max of latencies in milliseconds."""
    values = sorted(latencies_ms)
    if not values:
        return {"count": 0}
    return {
        "count": len(values),
        "p50_ms": percentile(values, 50),
        "p99_ms": percentile(values, 99),
        "mean_ms": statistics.fmean(values),
        "max_ms": values[-1],
    }


IDLE_RECONNECT_S = 4.0
"""A connection idle this long is reopened before use (uvicorn closes idle ones after 5 s)."""
REQUEST_TIMEOUT_S = 30.0
"""A request not answered this long after its scheduled time counts as an error (one that
found no free connection by then is not sent at all), so an overloaded run still ends."""


def process_cpu_s(pids: list[int]) -> float:
    """CPU seconds (user + system) the processes ``pids`` have used so far (a process that
    has exited counts 0)."""
    total = 0.0
    for pid in pids:
        try:
            times = psutil.Process(pid).cpu_times()
        except psutil.Error:
            continue
        total += times.user + times.system
    return total


def machine_busy_s() -> float:
    """CPU seconds every core of the machine has been busy so far (all but idle and
    iowait)."""
    times = psutil.cpu_times()
    return sum(times) - times.idle - getattr(times, "iowait", 0.0)


class CpuSampler:
    """CPU time of the watched processes, of this process and of the machine, summed per
    route over the blocks (sampled at each block's start and end)."""

    def __init__(self, pids: list[int]) -> None:
        self.pids = pids
        self.totals: dict[str, dict[str, float]] = {}
        self._start: tuple[float, float, float, float] | None = None

    @staticmethod
    def _now(pids: list[int]) -> tuple[float, float, float, float]:
        return time.perf_counter(), process_cpu_s(pids), time.process_time(), machine_busy_s()

    def start(self) -> None:
        self._start = self._now(self.pids)

    def stop(self, route: str) -> None:
        assert self._start is not None
        end = self._now(self.pids)
        total = self.totals.setdefault(
            route, {"wall_s": 0.0, "api_cpu_s": 0.0, "generator_cpu_s": 0.0, "machine_busy_s": 0.0}
        )
        for key, before, after in zip(total, self._start, end, strict=True):
            total[key] += after - before
        self._start = None

    def summary(self, route: str, requests: int) -> dict[str, float]:
        """The route's CPU ms per request (api, generator) and the busy cores meanwhile."""
        total = self.totals[route]
        return {
            "api_cpu_ms_per_request": 1000 * total["api_cpu_s"] / requests,
            "generator_cpu_ms_per_request": 1000 * total["generator_cpu_s"] / requests,
            "api_cores": total["api_cpu_s"] / total["wall_s"],
            "machine_busy_cores": total["machine_busy_s"] / total["wall_s"],
        }


class Connection:
    """One keep-alive HTTP/1.1 connection, written by hand: a request costs this process
    tens of microseconds, so the generator keeps its schedule where httpx's asyncio client
    fell behind on this shared machine."""

    def __init__(self, host: str, port: int) -> None:
        self.host, self.port = host, port
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None
        self.last_used = 0.0

    async def open(self) -> None:
        self.close()
        self.reader, self.writer = await asyncio.open_connection(self.host, self.port)
        self.last_used = time.perf_counter()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        self.reader = self.writer = None

    async def get(self, request: bytes) -> int:
        """Send ``request``; read the whole answer; its status code."""
        if self.writer is None or time.perf_counter() - self.last_used > IDLE_RECONNECT_S:
            await self.open()
        assert self.reader is not None and self.writer is not None
        self.writer.write(request)
        status_line = await self.reader.readline()
        if not status_line:
            raise ConnectionError("connection closed by the server")
        status = int(status_line.split()[1])
        length, chunked = 0, False
        while (line := await self.reader.readline()) not in (b"\r\n", b""):
            name, _, value = line.decode("latin-1").partition(":")
            if name.lower() == "content-length":
                length = int(value)
            elif name.lower() == "transfer-encoding" and "chunked" in value.lower():
                chunked = True
        if chunked:
            while (size := int((await self.reader.readline()).split(b";")[0], 16)) > 0:
                await self.reader.readexactly(size + 2)
            await self.reader.readline()
        else:
            await self.reader.readexactly(length)
        self.last_used = time.perf_counter()
        return status


async def _drive(
    urls: dict[str, str],
    token: str,
    rate: float,
    duration_s: float,
    blocks: int,
    connections: int,
    watch_pids: list[int] | None = None,
) -> dict[str, Any]:
    """Alternate blocks of ``JOBS_ROUTE`` on each server of ``urls`` (``list``, ``bare``:
    its URL) at ``rate`` requests/s each, ``duration_s`` per server in total; open loop,
    latency from the scheduled send time. Requests wait for a free connection of that
    server's pool (that wait is part of the latency). With ``watch_pids``, each server's
    CPU per request too (:class:`CpuSampler`)."""
    requests: dict[str, bytes] = {}
    pools: dict[str, asyncio.Queue[Connection]] = {}
    for route, url in urls.items():
        parsed = urlsplit(url)
        host, port = parsed.hostname or "127.0.0.1", parsed.port or 80
        requests[route] = (
            f"GET {JOBS_ROUTE} HTTP/1.1\r\nHost: {host}:{port}\r\n"
            f"Authorization: Bearer {token}\r\nAccept: application/json\r\n\r\n"
        ).encode()
        pools[route] = asyncio.Queue()
        for _ in range(connections):
            conn = Connection(host, port)
            await conn.open()
            pools[route].put_nowait(conn)
    block_s = duration_s / blocks
    per_block = round(rate * block_s)
    latencies: dict[str, list[float]] = {route: [] for route in urls}
    errors: dict[str, dict[str, int]] = {route: {} for route in urls}
    late_ms: list[float] = []

    async def one(route: str, scheduled: float) -> None:
        late_ms.append(1000 * (time.perf_counter() - scheduled))
        pool = pools[route]
        try:
            conn = await asyncio.wait_for(
                pool.get(), scheduled + REQUEST_TIMEOUT_S - time.perf_counter()
            )
        except TimeoutError:  # never sent: no connection came free in time
            errors[route]["not sent within timeout"] = (
                errors[route].get("not sent within timeout", 0) + 1
            )
            latencies[route].append(1000 * (time.perf_counter() - scheduled))
            return
        try:
            remaining = max(0.001, scheduled + REQUEST_TIMEOUT_S - time.perf_counter())
            kind = str(await asyncio.wait_for(conn.get(requests[route]), remaining))
        except (OSError, ValueError, asyncio.IncompleteReadError, TimeoutError) as exc:
            kind = type(exc).__name__
            conn.close()
        finally:
            pool.put_nowait(conn)
        latencies[route].append(1000 * (time.perf_counter() - scheduled))
        if kind != "200":
            errors[route][kind] = errors[route].get(kind, 0) + 1

    for route in urls:  # warm the connections and the servers
        await asyncio.gather(*(one(route, time.perf_counter()) for _ in range(connections)))
    for values in (*latencies.values(), late_ms):
        values.clear()
    for counts in errors.values():
        counts.clear()
    tasks: list[asyncio.Task[None]] = []
    cpu = CpuSampler(watch_pids or [])
    started = time.perf_counter()
    order = list(urls)
    for block in range(len(order) * blocks):
        route = order[block % len(order)]
        block_start = started + block * block_s
        block_tasks = []
        cpu.start()
        for i in range(per_block):
            scheduled = block_start + i / rate
            delay = scheduled - time.perf_counter()
            if delay > 0:
                await asyncio.sleep(delay)
            block_tasks.append(asyncio.create_task(one(route, scheduled)))
        # the block ends when its last request is answered or the next block begins
        next_block = block_start + block_s - time.perf_counter()
        if next_block > 0:
            await asyncio.wait(block_tasks, timeout=next_block)
        cpu.stop(route)
        tasks.extend(block_tasks)
    await asyncio.gather(*tasks)
    elapsed = time.perf_counter() - started
    for pool in pools.values():
        while not pool.empty():
            pool.get_nowait().close()
    routes = {}
    for route, values in latencies.items():
        routes[route] = {
            **latency_summary(values),
            "errors": sum(errors[route].values()),
            "error_kinds": errors[route],
            **({"cpu": cpu.summary(route, len(values))} if watch_pids else {}),
        }
    late = sorted(late_ms)
    return {
        "routes": routes,
        "connections": connections,
        "wall_s": elapsed,
        "send_lag_ms": {"p50": percentile(late, 50), "p99": percentile(late, 99)},
    }


def main(argv: list[str] | None = None) -> None:
    """``python -m benchmarks.api_load --url URL --bare-url URL ...`` (token on stdin): JSON
    on stdout."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.api_load")
    parser.add_argument("--url", required=True, help="the api")
    parser.add_argument("--bare-url", required=True, help="the bare app (benchmarks.api_bare)")
    parser.add_argument("--rate", type=float, default=200.0, help="requests/s")
    parser.add_argument("--duration", type=float, default=30.0, help="seconds per route")
    parser.add_argument("--blocks", type=int, default=6, help="alternating blocks per route")
    parser.add_argument("--connections", type=int, default=32, help="keep-alive connections")
    parser.add_argument(
        "--watch-pids",
        default="",
        help="comma-separated process ids of both servers: CPU per request",
    )
    args = parser.parse_args(argv)
    token = sys.stdin.readline().strip()
    pids = [int(pid) for pid in args.watch_pids.split(",") if pid]
    result = asyncio.run(
        _drive(
            {LIST: args.url, BARE: args.bare_url},
            token,
            args.rate,
            args.duration,
            args.blocks,
            args.connections,
            pids,
        )
    )
    json.dump(result, sys.stdout)


if __name__ == "__main__":
    main()
