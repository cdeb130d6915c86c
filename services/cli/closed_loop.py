"""The closed loop run from this process, for ``bgrl demo`` and ``bgrl bench loop``: the sim,
EEG and learner services as child processes (as ``bgrl up`` starts them), the worker runtime
that runs the jobs in-process, the rows ``POST /api/v1/sessions/{id}/start`` writes, and a
live run's latencies read back from its rows."""

from __future__ import annotations

import os
import socket
import sys
import time
from datetime import timedelta
from pathlib import Path
from typing import Any

SERVICES = {
    "sim": "services.sim.app:app",
    "eeg": "services.eeg.service.app:app",
    "learner": "services.learner.service.app:app",
}


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def wait_healthy(url: str, timeout_s: float = 180.0) -> None:
    import httpx

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"{url}/health", timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.3)
    raise RuntimeError(f"{url} did not become healthy within {timeout_s:g} s")


def start_services(data_dir: Path, token: str) -> tuple[dict[str, str], list[Any]]:
    """The sim, EEG and learner services as child processes (``bgrl up``'s :class:`Child`)."""
    from services.cli.serve import Child

    env = {
        **{k: v for k, v in os.environ.items() if not k.startswith("BGRL_")},
        "BGRL_DATA_DIR": str(data_dir),
        "BGRL_SERVICE_TOKEN": token,
        "BGRL_LOG_LEVEL": "WARNING",
    }
    urls, children = {}, []
    saved = dict(os.environ)
    os.environ.clear()
    os.environ.update(env)  # Child inherits this process's environment
    try:
        for name, app in SERVICES.items():
            port = free_port()
            urls[name] = f"http://127.0.0.1:{port}"
            cmd = [sys.executable, "-m", "uvicorn", app, "--host", "127.0.0.1", "--port", str(port),
                   "--no-access-log", "--log-level", "warning"]  # fmt: skip
            child = Child(name, cmd)
            child.start()
            children.append(child)
    finally:
        os.environ.clear()
        os.environ.update(saved)
    for url in urls.values():
        wait_healthy(url)
    return urls, children


def job_runtime(data_dir: Path) -> Any:
    """The worker runtime that runs this command's jobs in-process, set up as a ``bgrl
    worker`` process is: database migrated, torch limited to ``worker_torch_threads``
    intra-op threads (1 by default; the default of one per core spins for tens of ms per
    small op when the cores are shared, which made the demo's PPO and EEGNet training
    several times slower)."""
    import torch

    from services.core.db.migrate import upgrade_database
    from services.core.queue import make_celery
    from services.worker.runtime import Runtime
    from services.worker.settings import WorkerSettings

    settings = WorkerSettings(data_dir=data_dir)
    upgrade_database(settings.resolved_database_url)
    torch.set_num_threads(settings.worker_torch_threads)
    return Runtime(settings=settings, celery=make_celery(settings))


def cpu_seconds(children: list[Any]) -> dict[str, float]:
    """CPU time (user + system, s) used so far by this process and each service child: on
    a shared machine, the wall time a run would take on idle cores is bounded by these."""
    import resource

    own = resource.getrusage(resource.RUSAGE_SELF)
    out = {"demo": round(own.ru_utime + own.ru_stime, 1)}
    ticks = os.sysconf("SC_CLK_TCK")
    for child in children:
        try:
            fields = Path(f"/proc/{child.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
            out[child.name] = round((int(fields[11]) + int(fields[12])) / ticks, 1)
        except (OSError, IndexError, ValueError):
            continue
    return out


def lab_session(runtime: Any, kind: str, subject_id: int) -> int:
    from services.core.db.base import utcnow
    from services.core.db.models import LabSession

    with runtime.sessions() as db:
        start = utcnow()
        lab = LabSession(
            subject_id=subject_id,
            kind=kind,
            scheduled_at=start,
            duration_minutes=120,
            ends_at=start + timedelta(minutes=120),
        )
        db.add(lab)
        db.commit()
        return lab.id


def add_job(runtime: Any, kind: str, config: dict[str, Any]) -> str:
    from services.core.db.models import Job

    with runtime.sessions() as db:
        job = Job(kind=kind, config=config, status="queued")
        db.add(job)
        db.commit()
        return job.id


def live_run(runtime: Any, session_id: int, mode: str, options: dict[str, Any]) -> tuple[int, str]:
    """What ``POST /api/v1/sessions/{id}/start`` writes: the live run and its job."""
    from services.core.db.live import LiveRun, queue_live_job
    from services.platform.jobs import LIVE_SESSION

    with runtime.sessions() as db:
        run = LiveRun(session_id=session_id, mode=mode, options=options, status="queued")
        db.add(run)
        db.flush()
        job = queue_live_job(db, run, LIVE_SESSION.name)
        db.commit()
        return run.id, job.id


def run_to_end(runtime: Any, job_id: str, handler: Any) -> dict[str, Any]:
    """Run job ``job_id`` with ``handler`` in this process; its result (RuntimeError if it
    did not succeed)."""
    from services.core.db.models import Job
    from services.worker.runtime import run_job

    status = run_job(runtime, job_id, handler)
    with runtime.sessions() as db:
        job = db.get(Job, job_id)
        assert job is not None
        if status != "succeeded":
            raise RuntimeError(f"{job.kind} job {job_id} {status}: {job.error}")
        return dict(job.result or {})


def run_latencies(runtime: Any, run_id: int) -> dict[str, Any]:
    """Latency percentiles (ms) of a live run from its rows (``marker_to_frame_shown``: from
    the frames the subject display reported, if one was open)."""
    from sqlalchemy import select

    from services.core.db.live import LiveDecision, LiveFrameShown, LiveMarker, LiveModelVersion
    from services.core.live import latency_summary, timeline_latencies

    with runtime.sessions() as db:
        markers = {
            s: (ts, at.timestamp())
            for s, ts, at in db.execute(
                select(LiveMarker.step, LiveMarker.marker_ts, LiveMarker.executed_at).where(
                    LiveMarker.run_id == run_id
                )
            )
        }
        decisions = {
            s: (end, dec)
            for s, end, dec in db.execute(
                select(LiveDecision.step, LiveDecision.epoch_end_ts, LiveDecision.decided_ts).where(
                    LiveDecision.run_id == run_id
                )
            )
        }
        versions = {
            s: (up, ready)
            for s, up, ready in db.execute(
                select(
                    LiveModelVersion.step,
                    LiveModelVersion.updated_ts,
                    LiveModelVersion.next_ready_ts,
                ).where(LiveModelVersion.run_id == run_id)
            )
        }
        frames = [
            shown.timestamp() - markers[step][1]
            for step, shown in db.execute(
                select(LiveFrameShown.step, LiveFrameShown.shown_at).where(
                    LiveFrameShown.run_id == run_id
                )
            )
            if step in markers
        ]
    return latency_summary(timeline_latencies(markers, decisions, versions, frames))
