"""``bgrl bench soak``: ``bgrl up`` under a steady load while random processes are SIGKILLed.

The platform runs as a lab runs it (``bgrl up``, embedded SQLite and file broker, two job
workers) in a folder of its own. For ``minutes`` a client submits a small guided-PPO job
every ``job_every_s``, uploads a virtual subject's short calibration recording (a SYNTHETIC
BDF) to a lab session every ``upload_every_s``, and reads the job list every second (the
dashboard's hot read), while
every ``kill_every_s`` a process of a random kind (an api process, the sim, EEG or learner
service, a job worker) is killed with SIGKILL. Then the jobs get ``drain_s`` to end, ``bgrl
up`` is stopped, and the report counts:

- jobs submitted / succeeded / failed with a reason / **lost** (not ended, or failed
  without a reason: must be 0);
- uploads submitted / stored (201) / refused with the reason / unanswered (an api process
  killed mid-upload: the client would send it again) / **lost** (stored, but afterwards
  missing or with another SHA-256: must be 0);
- **orphans**: processes of the platform still alive 10 s after ``bgrl up`` stopped (0);
- restarts per kind (``bgrl up``'s status file), the p99 of the reads, the reads that got
  no answer (an api process killed mid-request), and each kind's RSS over time with its
  growth per hour (a line fitted to the samples), plotted.

Not in the mix yet: live sessions (they need a virtual subject streaming each; their
restarts are covered by the tests of ``bgrl up``).
"""

from __future__ import annotations

import hashlib
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import psutil

KINDS = ("api", "sim", "eeg", "learner", "worker")
MARKS = {
    "api": "services.api.app:app",
    "sim": "services.sim.app:app",
    "eeg": "services.eeg.service.app:app",
    "learner": "services.learner.service.app:app",
    "worker": "services.cli.main worker",
}
"""What a process's command line holds, by kind."""
FINAL = ("succeeded", "failed", "cancelled")
JOB_CONFIG = {
    "task": "SSSG",
    "method": "hf_sparse",
    "accuracy": 0.7,
    "ppo": {"n_epochs": 4, "eval_every": 256},
}
"""A small guided-PPO job (``job_steps`` env steps); each gets its own seed."""
UPLOAD_ACTIONS = 4
"""Actions in the uploaded recording: a virtual subject's calibration of about 8 s."""


def virtual_recording(folder: Path, seed: int) -> Path:
    """A virtual subject's short calibration recording (SYNTHETIC), as a 24-bit BDF file."""
    from services.eeg.recordings.io import write_bdf
    from services.eeg.virtual.subject import SyntheticRecording

    labels = [action % 3 != 0 for action in range(UPLOAD_ACTIONS)]
    recording = SyntheticRecording(labels, quality=0.6, seed=seed)
    return write_bdf(recording, folder / "virtual-subject.bdf")


def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def platform_processes(root: int) -> dict[int, str]:
    """Every live process below ``root`` that is a platform process: pid -> kind."""
    found = {}
    try:
        below = psutil.Process(root).children(recursive=True)
    except psutil.Error:
        return found
    for proc in below:
        try:
            command = " ".join(proc.cmdline())
        except psutil.Error:
            continue
        kind = next((k for k, mark in MARKS.items() if mark in command), None)
        if kind is not None:
            found[proc.pid] = kind
    return found


def rss_by_kind(processes: dict[int, str]) -> dict[str, float]:
    """MiB of resident memory of each kind (the sum of its processes)."""
    total: dict[str, float] = defaultdict(float)
    for pid, kind in processes.items():
        try:
            total[kind] += psutil.Process(pid).memory_info().rss / 2**20
        except psutil.Error:
            continue
    return dict(total)


def growth_per_hour(samples: list[tuple[float, float]]) -> float | None:
    """MiB per hour of a line fitted to ``(seconds, MiB)`` samples (None: too few)."""
    if len(samples) < 3:
        return None
    t, mib = np.array(samples).T
    return float(np.polyfit(t / 3600.0, mib, 1)[0])


def run_soak(
    out: Path,
    *,
    minutes: float,
    kill_every_s: float,
    job_every_s: float,
    drain_s: float,
    seed: int,
    upload_every_s: float = 15.0,
    job_steps: int = 1024,
    settings: dict[str, str] | None = None,
    progress: Callable[[str], None] = lambda _: None,
) -> dict[str, Any]:
    """Run the soak in ``out``; the report. The platform's data folder and ``bgrl up``'s log
    go to a new folder ``out/soak-*`` of each run.
    ``settings``: more ``BGRL_*`` variables for ``bgrl up`` (the rest of this process's
    ``BGRL_*`` are left out)."""
    rng = random.Random(seed)
    run_dir = Path(tempfile.mkdtemp(prefix="soak-", dir=out))
    ports = {name: _free_port() for name in ("api", "sim", "eeg", "learner")}
    env = {k: v for k, v in os.environ.items() if not k.startswith("BGRL_")}
    env.update(
        BGRL_DATA_DIR=str(run_dir / "data"),
        BGRL_PORT=str(ports["api"]),
        BGRL_SIM_PORT=str(ports["sim"]),
        BGRL_EEG_PORT=str(ports["eeg"]),
        BGRL_LEARNER_PORT=str(ports["learner"]),
        BGRL_WORKERS="2",
        BGRL_JOB_LEASE_S="10",
        BGRL_JOB_HEARTBEAT_S="1",
        BGRL_REAPER_INTERVAL_S="1",
        BGRL_LOG_LEVEL="WARNING",
    )
    env.update(settings or {})
    with (run_dir / "up.log").open("wb") as sink:
        up = subprocess.Popen(
            [sys.executable, "-m", "services.cli.main", "up"],
            env=env,
            stdout=sink,
            stderr=subprocess.STDOUT,
        )
    base = f"http://127.0.0.1:{ports['api']}"
    try:
        config = {**JOB_CONFIG, "total_steps": job_steps}
        recording = virtual_recording(run_dir, seed).read_bytes()
        timing = (minutes, kill_every_s, job_every_s, upload_every_s, drain_s)
        return _soak(up, base, out, run_dir, rng, config, recording, *timing, progress)
    finally:
        if up.poll() is None:
            up.kill()


def _soak(
    up: subprocess.Popen[bytes],
    base: str,
    out: Path,
    run_dir: Path,
    rng: random.Random,
    job_config: dict[str, Any],
    recording: bytes,
    minutes: float,
    kill_every_s: float,
    job_every_s: float,
    upload_every_s: float,
    drain_s: float,
    progress: Callable[[str], None],
) -> dict[str, Any]:
    log = run_dir / "up.log"
    deadline = time.monotonic() + 600
    while "Ctrl-C stops everything." not in log.read_text(errors="replace"):
        if up.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"bgrl up did not start; see {log}")
        time.sleep(1)
    progress("platform up")
    password = (run_dir / "data" / "first-admin-password").read_text().strip()
    client = httpx.Client(base_url=base, timeout=30)
    answer = client.post(
        "/api/v1/auth/token", data={"username": "admin@localhost", "password": password}
    )
    answer.raise_for_status()
    client.headers["Authorization"] = f"Bearer {answer.json()['access_token']}"
    lab_session = _lab_session(client)
    uploads = Uploads(client, lab_session, recording)

    started = time.monotonic()
    end = started + minutes * 60
    jobs: list[str] = []
    refused = 0
    reads: list[float] = []
    unanswered = 0
    kills: list[dict[str, Any]] = []
    rss: dict[str, list[tuple[float, float]]] = defaultdict(list)
    next_job, next_rss, next_kill = started, started, started + kill_every_s / 2
    next_upload = started + upload_every_s / 3
    while time.monotonic() < end:
        now = time.monotonic()
        if now >= next_job:
            next_job += job_every_s
            config = {**job_config, "seed": len(jobs) + 1}
            try:
                sent = client.post("/api/v1/jobs", json={"kind": "guided_ppo", "config": config})
                if sent.status_code == 201:
                    jobs.append(sent.json()["id"])
                else:
                    refused += 1
            except httpx.HTTPError:
                refused += 1  # an api process killed mid-request: the client's retry
        if now >= next_upload:
            next_upload += upload_every_s
            uploads.send()
        if now >= next_kill:
            next_kill += kill_every_s
            processes = platform_processes(up.pid)
            kinds = sorted(set(processes.values()))
            if kinds:
                kind = rng.choice(kinds)
                pid = rng.choice(sorted(p for p, k in processes.items() if k == kind))
                os.kill(pid, signal.SIGKILL)
                kills.append({"at_s": round(now - started, 1), "kind": kind, "pid": pid})
                progress(f"killed {kind} ({len(kills)} kills, {len(jobs)} jobs)")
        if now >= next_rss:
            next_rss += 5
            for kind, mib in rss_by_kind(platform_processes(up.pid)).items():
                rss[kind].append((now - started, mib))
        asked = time.perf_counter()
        try:
            client.get("/api/v1/jobs", params={"limit": 20}).raise_for_status()
            reads.append(time.perf_counter() - asked)
        except httpx.HTTPError:
            unanswered += 1
        time.sleep(max(0.0, 1.0 - (time.perf_counter() - asked)))

    progress("draining")
    statuses: dict[str, dict[str, Any]] = {}
    drain_end = time.monotonic() + drain_s
    while time.monotonic() < drain_end:
        try:
            statuses = {j: client.get(f"/api/v1/jobs/{j}").json() for j in jobs}
        except (httpx.HTTPError, ValueError):
            time.sleep(2)
            continue
        if all(s.get("status") in FINAL for s in statuses.values()):
            break
        time.sleep(3)
    upload_report = uploads.report()
    state = json.loads((run_dir / "data" / "run" / "processes.json").read_text())["processes"]
    restarts: dict[str, int] = defaultdict(int)
    for process in state.values():
        restarts[process["kind"]] += process["restarts"]
    tree = platform_processes(up.pid)
    up.send_signal(signal.SIGTERM)
    up.wait(timeout=60)
    time.sleep(10)
    orphans = sorted(p for p in tree if psutil.pid_exists(p) and _not_zombie(p))

    ended = [s for s in statuses.values() if s.get("status") in FINAL]
    failed = [s for s in ended if s["status"] == "failed"]
    with_reason = [s for s in failed if s.get("error")]
    lost = len(jobs) - len(ended) + (len(failed) - len(with_reason))
    report = {
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "minutes": minutes,
        "kill_every_s": kill_every_s,
        "job_every_s": job_every_s,
        "job_config": job_config,
        "cpu_count": os.cpu_count(),
        "folder": str(run_dir),
        "jobs": {
            "submitted": len(jobs),
            "refused_or_unanswered": refused,
            "succeeded": sum(s["status"] == "succeeded" for s in ended),
            "failed_with_reason": len(with_reason),
            "cancelled": sum(s["status"] == "cancelled" for s in ended),
            "lost": lost,
            "failure_reasons": sorted({str(s["error"])[:120] for s in with_reason}),
        },
        "uploads": upload_report,
        "orphans": len(orphans),
        "kills": {kind: sum(k["kind"] == kind for k in kills) for kind in KINDS},
        "restarts": {kind: restarts.get(kind, 0) for kind in KINDS},
        "reads": {
            "count": len(reads),
            "unanswered": unanswered,
            "p50_ms": round(1000 * float(np.percentile(reads, 50)), 1) if reads else None,
            "p99_ms": round(1000 * float(np.percentile(reads, 99)), 1) if reads else None,
        },
        "rss_mib": {
            kind: {
                "last": round(samples[-1][1], 1),
                "max": round(max(m for _, m in samples), 1),
                "growth_per_hour": _rounded(growth_per_hour(samples)),
            }
            for kind, samples in sorted(rss.items())
        },
        "kill_log": kills,
    }
    _plot(rss, kills, out / "soak_rss.png")
    return report


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(value, 1)


def _not_zombie(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def _plot(
    rss: dict[str, list[tuple[float, float]]], kills: list[dict[str, Any]], path: Path
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    for kind, samples in sorted(rss.items()):
        t, mib = np.array(samples).T
        ax.plot(t / 60, mib, label=kind)
    for kill in kills:
        ax.axvline(kill["at_s"] / 60, color="0.85", linewidth=0.8, zorder=0)
    ax.set_xlabel("minutes (grey: a process killed)")
    ax.set_ylabel("RSS, MiB (sum of the kind's processes)")
    ax.set_title("bgrl up under load with random SIGKILLs")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _lab_session(client: httpx.Client) -> int:
    """A new subject's calibration session, the uploads' destination; its id."""
    code = f"SOAK{datetime.now(UTC):%H%M%S}"
    subject = client.post("/api/v1/subjects", json={"code": code})
    subject.raise_for_status()
    session = client.post(
        "/api/v1/sessions",
        json={
            "subject_id": subject.json()["id"],
            "kind": "calibration",
            "scheduled_at": datetime.now(UTC).isoformat(),
        },
    )
    session.raise_for_status()
    return int(session.json()["id"])


class Uploads:
    """The soak's recording uploads: sends one BDF file again and again, then checks that
    every upload the api acknowledged is still there with the same SHA-256."""

    def __init__(self, client: httpx.Client, session_id: int, recording: bytes) -> None:
        self.client = client
        self.path = f"/api/v1/sessions/{session_id}/recordings"
        self.recording = recording
        self.sha256 = hashlib.sha256(recording).hexdigest()
        self.stored: list[int] = []
        self.refusals: list[str] = []
        self.unanswered = 0

    def send(self) -> None:
        """One upload; a refusal keeps the api's status and message."""
        try:
            sent = self.client.post(
                self.path,
                params={"filename": "virtual-subject.bdf"},
                content=self.recording,
                headers={"Content-Type": "application/octet-stream"},
            )
        except httpx.HTTPError:
            self.unanswered += 1  # an api process killed mid-upload: the client's retry
            return
        if sent.status_code == 201:
            self.stored.append(int(sent.json()["id"]))
        else:
            self.refusals.append(f"{sent.status_code}: {sent.text[:120]}")

    def report(self) -> dict[str, Any]:
        """The counts, after the soak (the api answering); an acknowledged upload that is
        missing or changed is lost."""
        lost = 0
        for recording_id in self.stored:
            for _ in range(5):  # an api process may still be restarting
                try:
                    found = self.client.get(f"/api/v1/recordings/{recording_id}")
                    break
                except httpx.HTTPError:
                    time.sleep(2)
            else:
                raise RuntimeError("the api did not answer after the soak")
            if found.status_code != 200 or found.json().get("sha256") != self.sha256:
                lost += 1
        return {
            "submitted": len(self.stored) + len(self.refusals) + self.unanswered,
            "stored": len(self.stored),
            "refused_with_reason": len(self.refusals),
            "unanswered": self.unanswered,
            "lost": lost,
            "bytes_each": len(self.recording),
            "refusal_reasons": sorted(set(self.refusals)),
        }
