"""``bgrl bench soak``: ``bgrl up`` under a steady load while random processes are SIGKILLed.

The platform runs as a lab runs it (``bgrl up``, embedded SQLite and file broker, two job
workers) in a folder of its own. For ``minutes`` a client submits a small guided-PPO job
every ``job_every_s``, uploads a virtual subject's short calibration recording (a SYNTHETIC
BDF) to a lab session every ``upload_every_s``, starts a short accelerated calibration
session of a new virtual subject every ``live_every_s`` (its ``live_session`` job records
the EEG service's live recording and queues an ``eeg_calibration`` job on it), and reads
the job list every second (the dashboard's hot read), while every ``kill_every_s`` a
process of a random kind (an api process, the sim, EEG or learner service, a job worker) is
killed with SIGKILL. Then the jobs get ``drain_s`` to end, ``bgrl up`` is stopped, and the
report counts:

- jobs (the guided-PPO jobs, the live sessions' jobs and their ``eeg_calibration``
  follow-ups, also per kind) submitted / succeeded / failed with a reason / **lost** (not
  ended, or failed without a reason: must be 0);
- live sessions started / ended with their data (run completed, its markers and stored
  recording kept) / ended with the reason (run failed saying so, its rows kept) / **lost**
  (still running after the drain, or ended with neither: must be 0);
- uploads submitted / stored (201) / refused with the reason / unanswered (an api process
  killed mid-upload: the client would send it again) / **lost** (stored, but afterwards
  missing or with another SHA-256: must be 0);
- **orphans**: processes of the platform still alive 10 s after ``bgrl up`` stopped (0);
- restarts per kind (``bgrl up``'s status file), the p99 of the reads, the reads that got
  no answer (an api process killed mid-request), and RSS: every process's, sampled every
  ``RSS_EVERY_S``, with each kind's growth per hour (the median and the largest slope of a
  line fitted to each of its processes' samples over that process's life after its first
  ``RSS_WARMUP_S``; a killed process starts a new line), plotted per kind (the sum of its
  processes).
"""

from __future__ import annotations

import functools
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
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import psutil

from services.core.files import write_results_json
from services.core.lifetime import die_with_parent

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
SETTLE_S = 60.0
"""At most this long the report waits for killed processes still in their restart backoff."""
RSS_EVERY_S = 5.0
"""Seconds between two RSS samples of every process."""
RSS_WARMUP_S = 60.0
"""Seconds of a process's first samples left out of its growth (imports, first requests)."""
MIN_RSS_SAMPLES = 6
"""Samples of one process after its warm-up needed for its growth (a process killed sooner
has none)."""
LIVE_OPTIONS = {"accelerated": True, "virtual_quality": 0.7, "calibration_max_passes": 2}
"""A live session of the mix: an accelerated calibration with a virtual subject whose
``eeg_calibration`` follow-up trains briefly (``n_actions`` is the run's ``live_actions``;
a calibration needs 30 epochs or more)."""


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


def rss_by_process(processes: dict[int, str]) -> dict[int, float]:
    """MiB of resident memory of each process (pid -> MiB); a process gone is left out."""
    found = {}
    for pid in processes:
        try:
            found[pid] = psutil.Process(pid).memory_info().rss / 2**20
        except psutil.Error:
            continue
    return found


def rss_report(
    samples: dict[int, list[tuple[float, float]]], kinds: dict[int, str]
) -> dict[str, dict[str, Any]]:
    """Per kind: the last and largest sum of its processes' RSS (MiB), and the median and
    largest growth per hour of its processes that lived for ``MIN_RSS_SAMPLES`` samples."""
    report = {}
    for kind in sorted(set(kinds.values())):
        pids = [pid for pid, k in kinds.items() if k == kind]
        slopes = [
            g for pid in pids if (g := growth_per_hour(_after_warmup(samples[pid]))) is not None
        ]
        sums = kind_sums(samples, kinds, kind)
        report[kind] = {
            "last": round(sums[-1][1], 1) if sums else None,
            "max": round(max(m for _, m in sums), 1) if sums else None,
            "processes": len(pids),
            "processes_fitted": len(slopes),
            "growth_per_hour": _rounded(float(np.median(slopes)) if slopes else None),
            "growth_per_hour_max": _rounded(max(slopes) if slopes else None),
        }
    return report


def _after_warmup(samples: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The samples taken ``RSS_WARMUP_S`` or more after the process's first one."""
    if not samples:
        return samples
    first = samples[0][0]
    return [(t, mib) for t, mib in samples if t - first >= RSS_WARMUP_S]


def kind_sums(
    samples: dict[int, list[tuple[float, float]]], kinds: dict[int, str], kind: str
) -> list[tuple[float, float]]:
    """``(seconds, MiB)``: the sum of the kind's processes at each sampling time."""
    total: dict[float, float] = defaultdict(float)
    for pid, k in kinds.items():
        if k == kind:
            for at, mib in samples[pid]:
                total[at] += mib
    return sorted(total.items())


def growth_per_hour(samples: list[tuple[float, float]]) -> float | None:
    """MiB per hour of a line fitted to ``(seconds, MiB)`` samples (None: fewer than
    ``MIN_RSS_SAMPLES``)."""
    if len(samples) < MIN_RSS_SAMPLES:
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
    live_every_s: float = 30.0,
    live_actions: int = 30,
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
            # a soak killed (Ctrl-C, a timeout) takes its platform with it
            preexec_fn=functools.partial(die_with_parent, os.getpid(), signal.SIGTERM),
        )
    base = f"http://127.0.0.1:{ports['api']}"
    try:
        config = {**JOB_CONFIG, "total_steps": job_steps}
        recording = virtual_recording(run_dir, seed).read_bytes()
        every = Every(kill_every_s, job_every_s, upload_every_s, live_every_s)
        live_options = {**LIVE_OPTIONS, "n_actions": live_actions}
        return _soak(
            up, base, out, run_dir, rng, config, recording, live_options, minutes, every, drain_s,
            progress,
        )  # fmt: skip
    finally:
        if up.poll() is None:
            up.kill()


@dataclass(frozen=True)
class Every:
    """Seconds between two of each event of the mix."""

    kill_s: float
    job_s: float
    upload_s: float
    live_s: float


def _soak(
    up: subprocess.Popen[bytes],
    base: str,
    out: Path,
    run_dir: Path,
    rng: random.Random,
    job_config: dict[str, Any],
    recording: bytes,
    live_options: dict[str, Any],
    minutes: float,
    every: Every,
    drain_s: float,
    progress: Callable[[str], None],
) -> dict[str, Any]:
    log = run_dir / "up.log"
    launched = time.monotonic()
    deadline = launched + 600
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
    uploads = Uploads(client, _lab_session(client, "SOAK"), recording)
    live = LiveSessions(client, live_options)

    started = time.monotonic()
    end = started + minutes * 60
    jobs: list[str] = []
    refused = 0
    reads: list[float] = []
    unanswered = 0
    kills: list[dict[str, Any]] = []
    rss: dict[int, list[tuple[float, float]]] = defaultdict(list)
    kinds: dict[int, str] = {}
    next_job, next_rss, next_kill = started, started, started + every.kill_s / 2
    next_upload, next_live = started + every.upload_s / 3, started + every.live_s / 4
    while time.monotonic() < end:
        now = time.monotonic()
        if now >= next_job:
            next_job += every.job_s
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
            next_upload += every.upload_s
            uploads.send()
        if now >= next_live:
            next_live += every.live_s
            live.start()
        if now >= next_kill:
            next_kill += every.kill_s
            processes = platform_processes(up.pid)
            alive_kinds = sorted(set(processes.values()))
            if alive_kinds:
                kind = rng.choice(alive_kinds)
                pid = rng.choice(sorted(p for p, k in processes.items() if k == kind))
                # bgrl up's own children; the others (a Celery pool child) their parent replaces
                supervised = pid in {child.pid for child in psutil.Process(up.pid).children()}
                os.kill(pid, signal.SIGKILL)
                kills.append({"at_s": round(now - started, 1), "kind": kind, "pid": pid,
                              "supervised": supervised})  # fmt: skip
                progress(
                    f"killed {kind} ({len(kills)} kills, {len(jobs)} jobs, "
                    f"{len(live.sessions)} live sessions)"
                )
        if now >= next_rss:
            next_rss += RSS_EVERY_S
            processes = platform_processes(up.pid)
            kinds.update(processes)
            for pid, mib in rss_by_process(processes).items():
                rss[pid].append((round(now - started, 1), mib))
        asked = time.perf_counter()
        try:
            client.get("/api/v1/jobs", params={"limit": 20}).raise_for_status()
            reads.append(time.perf_counter() - asked)
        except httpx.HTTPError:
            unanswered += 1
        time.sleep(max(0.0, 1.0 - (time.perf_counter() - asked)))

    progress("draining")
    drained = time.monotonic()
    statuses = _drain(client, jobs, live, drain_s, progress)
    drained_s = time.monotonic() - drained
    upload_report = uploads.report()
    live_report = live.report()
    state = _settled_processes(run_dir / "data" / "run" / "processes.json")
    restarts: dict[str, int] = defaultdict(int)
    for process in state.values():
        restarts[process["kind"]] += process["restarts"]
    tree = platform_processes(up.pid)
    up.send_signal(signal.SIGTERM)
    up.wait(timeout=60)
    time.sleep(10)
    orphans = sorted(p for p in tree if psutil.pid_exists(p) and _not_zombie(p))

    report = {
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "minutes": minutes,
        "kill_every_s": every.kill_s,
        "job_every_s": every.job_s,
        "upload_every_s": every.upload_s,
        "live_every_s": every.live_s,
        "job_config": job_config,
        "live_options": live.options,
        "cpu_count": os.cpu_count(),
        "folder": str(run_dir),
        "seconds": {
            "start": round(started - launched, 1),
            "load": round(drained - started, 1),
            "drain": round(drained_s, 1),
        },
        "jobs": {
            **_job_counts(list(statuses.values())),
            "refused_or_unanswered": refused,
            "by_kind": {
                kind: _job_counts([s for s in statuses.values() if s["kind"] == kind])
                for kind in sorted({s["kind"] for s in statuses.values()})
            },
        },
        "uploads": upload_report,
        "live_sessions": live_report,
        "orphans": len(orphans),
        "kills": {kind: sum(k["kind"] == kind for k in kills) for kind in KINDS},
        "kills_of_supervised": sum(k["supervised"] for k in kills),
        "restarts": {kind: restarts.get(kind, 0) for kind in KINDS},
        "reads": {
            "count": len(reads),
            "unanswered": unanswered,
            "p50_ms": round(1000 * float(np.percentile(reads, 50)), 1) if reads else None,
            "p99_ms": round(1000 * float(np.percentile(reads, 99)), 1) if reads else None,
        },
        "rss_mib": rss_report(rss, kinds),
        "kill_log": kills,
    }
    write_results_json(out / "soak_rss.json", {"kinds": kinds, "samples": rss})
    _plot(rss, kinds, kills, out / "soak_rss.png")
    return report


def _drain(
    client: httpx.Client,
    jobs: list[str],
    live: LiveSessions,
    drain_s: float,
    progress: Callable[[str], None],
) -> dict[str, dict[str, Any]]:
    """Wait up to ``drain_s`` for every job (the soak's, the live sessions' and their
    follow-ups) to end; the last answer for each job (``kind`` and ``status`` at least)."""
    statuses: dict[str, dict[str, Any]] = {}
    drain_end = time.monotonic() + drain_s
    while True:
        try:
            tracked = jobs + live.job_ids()
            statuses = {j: client.get(f"/api/v1/jobs/{j}").json() for j in tracked}
        except (httpx.HTTPError, ValueError, RuntimeError):
            statuses = {}
        else:
            waiting = sorted(s["kind"] for s in statuses.values() if s.get("status") not in FINAL)
            if not waiting and live.settled():
                return statuses
            progress(f"draining: waiting for {len(waiting)} jobs ({', '.join(waiting)})")
        if time.monotonic() > drain_end:
            return statuses or {j: {"kind": "unknown", "status": "unanswered"} for j in jobs}
        time.sleep(3)


def _job_counts(statuses: list[dict[str, Any]]) -> dict[str, Any]:
    """Submitted, succeeded, failed with a reason, cancelled and lost among ``statuses``."""
    ended = [s for s in statuses if s.get("status") in FINAL]
    failed = [s for s in ended if s["status"] == "failed"]
    with_reason = [s for s in failed if s.get("error")]
    return {
        "submitted": len(statuses),
        "succeeded": sum(s["status"] == "succeeded" for s in ended),
        "failed_with_reason": len(with_reason),
        "cancelled": sum(s["status"] == "cancelled" for s in ended),
        "lost": len(statuses) - len(ended) + (len(failed) - len(with_reason)),
        "failure_reasons": sorted({str(s["error"])[:120] for s in with_reason}),
    }


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(value, 1)


def _settled_processes(status_file: Path, timeout_s: float = SETTLE_S) -> dict[str, Any]:
    """``bgrl up``'s processes once none is still coming back from a kill (a process killed
    just before the drain ended may be in its restart backoff), or as they are after
    ``timeout_s``; the counts of restarts are read from these."""
    deadline = time.monotonic() + timeout_s
    while True:
        processes: dict[str, Any] = json.loads(status_file.read_text())["processes"]
        coming_back = [p for p in processes.values() if p["state"] in ("starting", "restarting")]
        if not coming_back or time.monotonic() > deadline:
            return processes
        time.sleep(0.5)


def _not_zombie(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def _plot(
    rss: dict[int, list[tuple[float, float]]],
    kinds: dict[int, str],
    kills: list[dict[str, Any]],
    path: Path,
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    for kind in sorted(set(kinds.values())):
        sums = kind_sums(rss, kinds, kind)
        if sums:
            t, mib = np.array(sums).T
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


def _lab_session(client: httpx.Client, code: str) -> int:
    """A calibration session of a new subject ``code`` (made unique by the time); its id."""
    code = f"{code}{datetime.now(UTC):%H%M%S%f}"
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


class LiveSessions:
    """The soak's live sessions: starts an accelerated calibration session of a new virtual
    subject again and again, then sorts out how each ended."""

    def __init__(self, client: httpx.Client, options: dict[str, Any]) -> None:
        self.client = client
        self.options = options
        self.sessions: dict[int, str] = {}
        """Lab session id -> its live_session job id, for every start the api accepted."""
        self.refusals: list[str] = []
        self.unanswered = 0

    def start(self) -> None:
        """One session: a new subject's calibration session, then its live start."""
        try:
            session_id = _lab_session(self.client, f"SOAK-LIVE{len(self.sessions) + 1}-")
            sent = self.client.post(f"/api/v1/sessions/{session_id}/start", json=self.options)
        except httpx.HTTPError:
            self.unanswered += 1  # an api process killed mid-request: the client's retry
            return
        if sent.status_code == 201:
            self.sessions[session_id] = sent.json()["job_id"]
        else:
            self.refusals.append(f"{sent.status_code}: {sent.text[:120]}")

    def _runs(self) -> dict[int, dict[str, Any]]:
        """Each session's ``GET /sessions/{id}/live`` now (an api process may be restarting:
        asked again for up to 10 s)."""
        runs = {}
        for session_id in self.sessions:
            for _ in range(5):
                try:
                    answer = self.client.get(f"/api/v1/sessions/{session_id}/live")
                    answer.raise_for_status()
                    runs[session_id] = answer.json()
                    break
                except httpx.HTTPError:
                    time.sleep(2)
            else:
                raise RuntimeError("the api did not answer after the soak")
        return runs

    def job_ids(self) -> list[str]:
        """The live sessions' jobs and their ``eeg_calibration`` follow-ups known so far."""
        follow_ups = [
            live["run"]["follow_up_job_id"]
            for live in self._runs().values()
            if live["run"]["follow_up_job_id"] is not None
        ]
        return list(self.sessions.values()) + follow_ups

    def settled(self) -> bool:
        """No run is queued or running any more."""
        return all(
            live["run"]["status"] not in ("queued", "running") for live in self._runs().values()
        )

    def report(self) -> dict[str, Any]:
        """The counts after the soak: a run completed with its markers and its stored
        recording ended with its data; one failed saying its rows are kept ended with the
        reason; any other (still running, or ended with neither) is lost."""
        with_data = with_reason = lost = resumed = 0
        reasons = set()
        for live in self._runs().values():
            run = live["run"]
            resumed += run["resumes"] > 0
            if run["status"] == "completed" and live["markers"] > 0 and run["recording_id"]:
                with_data += 1
            elif run["status"] == "failed" and "are kept" in (run["error"] or ""):
                with_reason += 1
                reasons.add(str(run["error"])[:160])
            else:
                lost += 1
        return {
            "submitted": len(self.sessions) + len(self.refusals) + self.unanswered,
            "started": len(self.sessions),
            "ended_with_data": with_data,
            "ended_with_reason": with_reason,
            "lost": lost,
            "resumed_after_a_kill": resumed,
            "refused_with_reason": len(self.refusals),
            "unanswered": self.unanswered,
            "end_reasons": sorted(reasons),
            "refusal_reasons": sorted(set(self.refusals)),
        }
