"""``bgrl bench api``: the platform api under load, and job throughput through real workers.

Figures:

- **reads under load**: the api (``uvicorn services.api.app:app --workers N``, on
  loopback) with ``jobs_stored`` jobs in its database, and its peer: a bare FastAPI app
  (:mod:`benchmarks.api_bare`, run by uvicorn alike) whose one route answers the bytes the
  api's list gave, without middleware, sign-in, database or validation. A SECOND process
  sends ``rate`` requests/s, open loop (each request leaves at its scheduled time, whatever
  the earlier ones are doing), of ``GET /api/v1/jobs?limit=50`` (signed in) to each, in
  alternating blocks so load from other processes hits both alike. Latency is measured
  from the scheduled send time to the end of the response (so a client or server falling
  behind shows up), p50/p99 and errors per server and the ratio of the two p99s. Each load
  level gets a fresh api (a light level must not inherit a saturated one's backlog).
  SQLite, and PostgreSQL when it is reachable. The aim: the list's p99 under 50 ms at 200
  requests/s, without errors.
- **CPU per request**, in process: the list and its bare peer called straight through
  the ASGI app (no HTTP, no network, one at a time), CPU milliseconds per request: what
  the api costs whatever the machine's load, and its ratio to the bare answer.
- **RSS** of the api processes (uvicorn's and its workers', summed, psutil) when idle
  (started, signed in, jobs stored) and after the load.
- **job throughput**: short ``guided_ppo`` jobs (hf_sparse, ``total_steps`` 2000) per
  minute through 1 and then 2 ``bgrl worker`` processes (embedded filesystem broker,
  SQLite: what ``bgrl up`` runs), from the first commit to the last finish; **queue
  latency** (commit to start) of probe jobs submitted one at a time to idle workers (each
  cancelled once it has started; the time from cancel to stop is reported too), and the
  hand-over gap between one job's finish and the next one's start on a busy worker.

The load generator, the second process, is ``benchmarks/api_load.py``.
"""

from __future__ import annotations

import json
import math
import os
import platform
import secrets
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import httpx
import psutil

from benchmarks.api_bare import BODY_ENV
from benchmarks.api_cpu import cpu_ms_per_request
from benchmarks.api_data import (
    ADMIN_EMAIL,
    PG_SKIP_REASON,
    THROUGHPUT_CONFIG,
    postgres_schema,
    store_jobs,
)
from benchmarks.api_load import BARE, JOBS_ROUTE, LIST, latency_summary, percentile
from services.api.settings import default_api_workers
from services.client import Job, PlatformClient
from services.core.db.migrate import upgrade_database

Progress = Callable[[str], None]
AIM_P99_MS = 50.0
AIM_SPEEDUP_2_WORKERS = 1.7
STARTUP_TIMEOUT_S = 120.0


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _rss_mb(pid: int) -> float:
    """Resident set size of a process, in MiB."""
    return psutil.Process(pid).memory_info().rss / 2**20


def _process_tree(pid: int) -> list[int]:
    """``pid`` and its descendants."""
    return [pid, *(child.pid for child in psutil.Process(pid).children(recursive=True))]


def _platform_env(data_dir: Path, database_url: str, admin_password: str) -> dict[str, str]:
    """The environment of the bench's api and workers (nothing inherited from BGRL_*)."""
    base = {k: v for k, v in os.environ.items() if not k.startswith("BGRL_")}
    return {
        **base,
        "BGRL_DATA_DIR": str(data_dir),
        "BGRL_DATABASE_URL": database_url,
        "BGRL_ADMIN_EMAIL": ADMIN_EMAIL,
        "BGRL_ADMIN_PASSWORD": admin_password,
        "BGRL_EEG_URL": "",
        "BGRL_LOG_LEVEL": "WARNING",
    }


class Platform:
    """An api process (and worker processes) on one database and data folder."""

    def __init__(self, root: Path, database_url: str, *, api_workers: int = 1) -> None:
        self.root = root
        self.database_url = database_url
        self.api_workers = api_workers
        self.admin_password = secrets.token_urlsafe(16)
        self.env = _platform_env(root / "data", database_url, self.admin_password)
        self.port = _free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.api: subprocess.Popen[bytes] | None = None
        self.bare: subprocess.Popen[bytes] | None = None
        self.bare_port = _free_port()
        self.bare_url = f"http://127.0.0.1:{self.bare_port}"
        self.workers: list[subprocess.Popen[bytes]] = []

    def _spawn(
        self, name: str, args: list[str], extra_env: dict[str, str] | None = None
    ) -> subprocess.Popen[bytes]:
        log = (self.root / f"{name}.log").open("ab")
        return subprocess.Popen(
            [sys.executable, *args],
            env={**self.env, **(extra_env or {})},
            cwd=self.root,
            stdout=log,
            stderr=log,
        )

    def start_api(self) -> None:
        """Migrate, start uvicorn with ``api_workers`` processes (which do not migrate, as
        under ``bgrl up``) and wait until ``/readyz`` answers 200."""
        upgrade_database(self.database_url)
        self.api = self._spawn(
            "api",
            ["-m", "uvicorn", "services.api.app:app", "--host", "127.0.0.1",
             "--port", str(self.port), "--workers", str(self.api_workers),
             "--no-access-log", "--log-level", "warning"],
            extra_env={"BGRL_MIGRATE_ON_START": "false"},
        )  # fmt: skip
        self._wait_ready("api", self.api, f"{self.url}/readyz")

    def start_bare(self, body: bytes) -> None:
        """Start the bare app (:mod:`benchmarks.api_bare`) answering ``body``, with as many
        uvicorn processes as the api, and wait until it answers."""
        body_file = self.root / "bare-body.json"
        body_file.write_bytes(body)
        self.bare = self._spawn(
            "bare",
            ["-m", "uvicorn", "benchmarks.api_bare:app_from_env", "--factory",
             "--host", "127.0.0.1", "--port", str(self.bare_port),
             "--workers", str(self.api_workers), "--no-access-log", "--log-level", "warning"],
            extra_env={BODY_ENV: str(body_file)},
        )  # fmt: skip
        self._wait_ready("bare", self.bare, f"{self.bare_url}{JOBS_ROUTE}")

    def _wait_ready(self, name: str, proc: subprocess.Popen[bytes], url: str) -> None:
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"the {name} exited: {self.log(name)[-2000:]}")
            try:
                if httpx.get(url, timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"the {name} did not get ready: {self.log(name)[-2000:]}")
            time.sleep(0.2)

    def start_worker(self, name: str) -> None:
        """Start one ``bgrl worker`` process."""
        self.workers.append(
            self._spawn(name, ["-m", "services.cli.main", "worker", "--name", name])
        )

    def log(self, name: str) -> str:
        return (self.root / f"{name}.log").read_text(errors="replace")

    def client(self) -> PlatformClient:
        """A client signed in as the bench's admin with an API token (an access token
        expires after 30 minutes, shorter than the job phases)."""
        client = PlatformClient(self.url, timeout_s=60)
        client.login(ADMIN_EMAIL, self.admin_password)
        token = client.create_api_token("bench", expires_in_days=1).token
        assert token is not None
        client.login_with_api_token(token)
        return client

    def api_rss_mb(self) -> float:
        """RSS of uvicorn and its worker processes, summed."""
        assert self.api is not None
        return sum(_rss_mb(pid) for pid in _process_tree(self.api.pid))

    def stop(self) -> None:
        """SIGTERM everything started, SIGKILL what is left after 15 s."""
        procs = [*self.workers, *(p for p in (self.api, self.bare) if p is not None)]
        for proc in procs:
            if proc.poll() is None:
                proc.terminate()
        for proc in procs:
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def run_load(
    url: str,
    bare_url: str,
    token: str,
    *,
    rate: float,
    duration_s: float,
    blocks: int,
    watch_pids: list[int] | None = None,
) -> dict[str, Any]:
    """Run the load generator in a second process against the api at ``url`` and the bare
    app at ``bare_url``; its JSON summary (with each one's CPU per request of the processes
    ``watch_pids``)."""
    cmd = [
        sys.executable, "-m", "benchmarks.api_load", "--url", url, "--bare-url", bare_url,
        "--rate", str(rate), "--duration", str(duration_s), "--blocks", str(blocks),
        "--watch-pids", ",".join(str(pid) for pid in watch_pids or []),
    ]  # fmt: skip
    done = subprocess.run(
        cmd,
        input=token,
        capture_output=True,
        text=True,
        check=False,
        timeout=4 * duration_s + 120,
    )
    if done.returncode != 0:
        raise RuntimeError(f"load generator failed: {done.stderr[-2000:]}")
    return json.loads(done.stdout)


def _load_level(
    plat: Platform, token: str, rate: float, duration_s: float, blocks: int
) -> dict[str, Any]:
    """A fresh api on the platform's database and the bare app answering its list's bytes,
    the api's RSS idle, the load, its RSS after."""
    plat.start_api()
    try:
        rss_idle = plat.api_rss_mb()
        listed = httpx.get(
            f"{plat.url}{JOBS_ROUTE}", headers={"Authorization": f"Bearer {token}"}, timeout=30
        )
        listed.raise_for_status()
        plat.start_bare(listed.content)
        assert plat.api is not None and plat.bare is not None
        load = run_load(
            plat.url,
            plat.bare_url,
            token,
            rate=rate,
            duration_s=duration_s,
            blocks=blocks,
            watch_pids=_process_tree(plat.api.pid) + _process_tree(plat.bare.pid),
        )
        rss_after = plat.api_rss_mb()
    finally:
        plat.stop()
    jobs, bare = load["routes"][LIST], load["routes"][BARE]
    ratio = jobs["p99_ms"] / bare["p99_ms"] if bare.get("p99_ms") else None
    return {
        "rate_per_s": rate,
        **load,
        "list_p99_to_bare_p99": ratio,
        "meets_aim": bool(jobs.get("p99_ms", math.inf) < AIM_P99_MS and jobs["errors"] == 0),
        "api_rss_mb": {"idle": rss_idle, "after_load": rss_after},
    }


def bench_reads(
    database: str,
    database_url: str,
    root: Path,
    *,
    jobs_stored: int,
    rate: float,
    light_rate: float,
    duration_s: float,
    blocks: int,
    api_workers: int | None,
    progress: Progress,
) -> dict[str, Any]:
    """``jobs_stored`` jobs on ``database_url``; the load at ``rate``, then at ``light_rate``
    (what the server carries on this machine, for reference), each on a fresh api of
    ``api_workers`` processes (default: as many as `bgrl up` runs on that database); then
    the CPU per request in process."""
    if api_workers is None:
        api_workers = default_api_workers({"database_url": database_url})
    plat = Platform(root, database_url, api_workers=api_workers)
    try:
        plat.start_api()
        with plat.client() as client:
            store_jobs(database_url, jobs_stored)
            page = client.list_jobs(limit=50)
            assert page.total == jobs_stored, page.total
            token = client.token
    finally:
        plat.stop()
    assert token is not None
    progress(f"{database}: {jobs_stored} jobs stored")
    load = _load_level(plat, token, rate, duration_s, blocks)
    progress(f"{database}: load at {rate:g} req/s done")
    light = _load_level(plat, token, light_rate, duration_s, blocks)
    progress(f"{database}: load at {light_rate:g} req/s done")
    cpu = cpu_ms_per_request(database_url, root / "data", ADMIN_EMAIL, plat.admin_password)
    progress(f"{database}: CPU per request measured")
    return {
        "database": database,
        "jobs_stored": jobs_stored,
        "api_workers": api_workers,
        "load": load,
        "list_p99_to_bare_p99": load["list_p99_to_bare_p99"],
        "light_load": light,
        "meets_aim": load["meets_aim"],
        "api_rss_mb": load["api_rss_mb"],
        "cpu_ms_per_request_in_process": cpu,
    }


def _probe(client: PlatformClient, job_id: str, timeout_s: float) -> tuple[float, float]:
    """Wait until the job starts, cancel it and wait until it stops: (commit to start,
    cancel to stop), in seconds."""
    deadline = time.monotonic() + timeout_s
    job = client.get_job(job_id)
    while job.started_at is None:
        if job.finished or time.monotonic() > deadline:
            raise RuntimeError(f"probe job {job_id} {job.status} without starting")
        time.sleep(0.05)
        job = client.get_job(job_id)
    cancelled_at = time.monotonic()
    client.cancel_job(job_id)
    final = client.wait_job(job_id, timeout_s=timeout_s, poll_s=0.1)
    if final.status not in ("cancelled", "succeeded"):
        raise RuntimeError(f"probe job {job_id} {final.status}: {final.error}")
    queued_s = (job.started_at - job.created_at).total_seconds()
    return queued_s, time.monotonic() - cancelled_at


def _wait_all(client: PlatformClient, job_ids: list[str], timeout_s: float) -> list[Job]:
    deadline = time.monotonic() + timeout_s
    jobs = []
    for job_id in job_ids:
        jobs.append(client.wait_job(job_id, timeout_s=max(1.0, deadline - time.monotonic())))
    failed = [j for j in jobs if j.status != "succeeded"]
    if failed:
        raise RuntimeError(f"job {failed[0].id} {failed[0].status}: {failed[0].error}")
    return jobs


def _handover_gaps_s(jobs: list[Job]) -> list[float]:
    """Per worker slot: seconds from one job's finish to the next job's start (busy queue)."""
    ends = sorted(j.finished_at for j in jobs if j.finished_at)  # type: ignore[misc]
    starts = sorted(j.started_at for j in jobs if j.started_at)  # type: ignore[misc]
    gaps = []
    for start in starts:
        before = [end for end in ends if end <= start]
        if before:
            gaps.append((start - before[-1]).total_seconds())
            ends.remove(before[-1])
    return gaps


def bench_throughput(
    root: Path,
    *,
    job_config: dict[str, Any],
    batch: int,
    probes: int,
    progress: Progress,
    timeout_s: float,
) -> dict[str, Any]:
    """Jobs/min with 1 then 2 workers; queue latency of jobs sent to idle workers."""
    plat = Platform(root, f"sqlite:///{root / 'data' / 'bgrl.db'}")
    (root / "data").mkdir(parents=True, exist_ok=True)
    seed = iter(range(10**6))
    phases: dict[str, Any] = {}
    all_latencies: list[float] = []
    all_cancels: list[float] = []
    try:
        plat.start_api()
        with plat.client() as client:

            def submit(n: int) -> list[str]:
                return [
                    client.submit_job("guided_ppo", {**job_config, "seed": next(seed)}).id
                    for _ in range(n)
                ]

            for n_workers in (1, 2):
                while len(plat.workers) < n_workers:
                    plat.start_worker(f"bench-w{len(plat.workers) + 1}")
                # warm-up: one job per worker (imports, oracle cache, first-run costs)
                _wait_all(client, submit(n_workers), timeout_s)
                progress(f"{n_workers} worker(s) warm")
                started = time.monotonic()
                jobs = _wait_all(client, submit(batch * n_workers), timeout_s)
                wall = time.monotonic() - started
                first = min(j.created_at for j in jobs)
                last = max(j.finished_at for j in jobs if j.finished_at)
                span_s = (last - first).total_seconds()
                durations = [
                    (j.finished_at - j.started_at).total_seconds()
                    for j in jobs
                    if j.finished_at and j.started_at
                ]
                gaps = sorted(1000 * g for g in _handover_gaps_s(jobs))
                progress(f"{n_workers} worker(s): {len(jobs)} jobs in {span_s:.0f} s")
                latencies, cancels = [], []
                for _ in range(probes):
                    (probe_id,) = submit(1)
                    queued_s, cancel_s = _probe(client, probe_id, timeout_s)
                    latencies.append(1000 * queued_s)
                    cancels.append(cancel_s)
                all_latencies.extend(latencies)
                all_cancels.extend(cancels)
                progress(f"{n_workers} worker(s): {probes} queue-latency probes")
                phases[f"workers_{n_workers}"] = {
                    "workers": n_workers,
                    "jobs": len(jobs),
                    "span_s": span_s,
                    "client_wall_s": wall,
                    "jobs_per_minute": 60 * len(jobs) / span_s,
                    "job_run_s": {
                        "p50": statistics.median(durations),
                        "max": max(durations),
                    },
                    "handover_gap_ms": {
                        "p50": percentile(gaps, 50) if gaps else None,
                        "p99": percentile(gaps, 99) if gaps else None,
                        "count": len(gaps),
                    },
                    "queue_latency_idle_ms": latency_summary(latencies),
                    "cancel_to_stop_s": {"p50": statistics.median(cancels), "max": max(cancels)},
                }
    finally:
        plat.stop()
    one, two = phases["workers_1"], phases["workers_2"]
    speedup = two["jobs_per_minute"] / one["jobs_per_minute"]
    return {
        "config": job_config,
        "broker": "embedded filesystem (kombu)",
        "database": "sqlite",
        **phases,
        "speedup_2_workers": speedup,
        "aim_speedup": AIM_SPEEDUP_2_WORKERS,
        "meets_aim": speedup >= AIM_SPEEDUP_2_WORKERS,
        "queue_latency_idle_ms": latency_summary(all_latencies),
        "cancel_to_stop_s": {"p50": statistics.median(all_cancels), "max": max(all_cancels)},
    }


def bench_all_reads(
    root: Path,
    *,
    jobs_stored: int,
    rate: float,
    light_rate: float,
    duration_s: float,
    blocks: int,
    api_workers: int | None,
    progress: Progress,
) -> dict[str, Any]:
    """:func:`bench_reads` on SQLite, and on PostgreSQL when it is reachable."""
    kwargs = {"jobs_stored": jobs_stored, "rate": rate, "light_rate": light_rate,
              "duration_s": duration_s, "blocks": blocks, "api_workers": api_workers,
              "progress": progress}  # fmt: skip
    figures: dict[str, Any] = {}
    (root / "sqlite").mkdir()
    figures["sqlite"] = bench_reads(
        "sqlite", f"sqlite:///{root / 'sqlite' / 'bgrl.db'}", root / "sqlite", **kwargs
    )
    with postgres_schema() as pg_url:
        if pg_url is None:
            figures["postgresql"] = {"skipped": PG_SKIP_REASON}
            progress("postgresql: skipped")
        else:
            (root / "postgresql").mkdir()
            figures["postgresql"] = bench_reads("postgresql", pg_url, root / "postgresql", **kwargs)
    return figures


def run(
    *,
    rate: float = 200.0,
    light_rate: float = 25.0,
    duration_s: float = 30.0,
    blocks: int = 6,
    jobs_stored: int = 1000,
    batch: int = 2,
    probes: int = 5,
    job_method: str = "hf_sparse",
    job_steps: int = 2000,
    job_timeout_s: float = 1800.0,
    jobs: bool = True,
    api_workers: int | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Every api benchmark; the figures as a JSON-ready dict."""
    report: Progress = progress if progress is not None else (lambda _message: None)
    started = time.perf_counter()
    load_at_start = list(os.getloadavg())
    job_config: dict[str, Any] = {
        **THROUGHPUT_CONFIG,
        "method": job_method,
        "total_steps": job_steps,
    }
    if job_method != "hf_sparse":
        job_config.pop("accuracy")
    with tempfile.TemporaryDirectory(prefix="bgrl-bench-api-") as tmp:
        root = Path(tmp)
        reads = bench_all_reads(
            root, jobs_stored=jobs_stored, rate=rate, light_rate=light_rate,
            duration_s=duration_s, blocks=blocks, api_workers=api_workers,
            progress=report,
        )  # fmt: skip
        (root / "jobs").mkdir()
        throughput = (
            None
            if not jobs
            else bench_throughput(
                root / "jobs",
                job_config=job_config,
                batch=batch,
                probes=probes,
                progress=report,
                timeout_s=job_timeout_s,
            )
        )
    return {
        "benchmark": "api",
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "load_average_at_start": load_at_start,
            "load_average_at_end": list(os.getloadavg()),
        },
        "parameters": {
            "rate_per_s": rate,
            "light_rate_per_s": light_rate,
            "duration_s_per_route": duration_s,
            "blocks_per_route": blocks,
            "jobs_stored": jobs_stored,
            "api_workers": api_workers,
            "jobs_route": JOBS_ROUTE,
            "bare_peer": "benchmarks.api_bare (the same bytes from a bare FastAPI route)",
            "throughput_jobs_per_worker": batch,
            "queue_latency_probes_per_phase": probes,
        },
        "aims": {
            "reads_p99_ms": AIM_P99_MS,
            "speedup_2_workers": AIM_SPEEDUP_2_WORKERS,
        },
        "reads": reads,
        "throughput": throughput,
        "wall_time_s": time.perf_counter() - started,
    }
