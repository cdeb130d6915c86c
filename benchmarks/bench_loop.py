"""``bgrl bench loop``: the closed loop's timing and learning with the virtual subject.

1. Accelerated, per virtual-subject quality: a calibration session, its classifier, then an
   online session of ``labels`` labels through the sim, EEG and learner services; reported:
   the classifier's held-out accuracy, the live decoding accuracy vs the oracle, pi_HF's SPL,
   and beside it ``bgrl hf-sweep``'s pi_HF SPL (simulated feedback) at the same accuracy.
2. Paced (one action every ``period_s`` on the wall clock, the virtual subject streaming in
   real time): the per-action timeline from the rows (marker -> epoch end, epoch end ->
   decision, decision -> learner update, update -> next action ready, epoch end -> next action
   ready, action executed -> frame shown) as p50/p99, and the pace's drift. The frame shown
   comes from the subject's real display page (``/sessions/{id}/display``, ``docs/live.md``),
   served by the api (started for it) and open in Debian's headless Chromium driven by
   Playwright, signed in through the api's login route as a lab's display machine is; it
   reports each frame it showed (``live_frames_shown``). Without Chromium or Playwright that
   figure is left out and ``paced.display.reason`` says why; the rest runs the same.

Writes ``OUT/loop.json`` and, with a paced session, ``OUT/loop_paced.png`` (its latencies).
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import resource
import secrets
import select
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from benchmarks.browser import CHROMIUM, CHROMIUM_ARGS
from services.cli.closed_loop import (
    cpu_seconds,
    free_port,
    job_runtime,
    lab_session,
    live_run,
    run_latencies,
    run_to_end,
    start_services,
    wait_healthy,
)

DISPLAY_OPEN_TIMEOUT_S = 180.0
"""Chromium's start and the page's first load (long on a loaded machine)."""
FRAMES_SETTLE_S = 3.0
"""After the last action, the display's reports are waited for until none arrives this long."""
BENCH_ADMIN = "bench-display@example.org"


def _subject(runtime: Any, code: str) -> int:
    from services.core.db.models import Subject

    with runtime.sessions() as db:
        subject = Subject(code=code, notes="virtual subject")
        db.add(subject)
        db.commit()
        return subject.id


def _classifier(
    runtime: Any, subject_id: int, quality: float, actions: int, max_passes: int | None
) -> dict[str, Any]:
    from services.worker.calibration import eeg_calibration
    from services.worker.live_session import live_session

    session_id = lab_session(runtime, "calibration", subject_id)
    options: dict[str, Any] = {
        "accelerated": True,
        "virtual_quality": quality,
        "n_actions": actions,
    }
    if max_passes is not None:
        options["calibration_max_passes"] = max_passes
    _, job_id = live_run(runtime, session_id, "calibration", options)
    calibration = run_to_end(runtime, job_id, live_session)
    return run_to_end(runtime, calibration["calibration_job_id"], eeg_calibration)


def display_unavailable() -> str | None:
    """Why the subject display cannot be opened on this machine (None: it can)."""
    if importlib.util.find_spec("playwright") is None:
        return "playwright (Python) is not installed: pip install -e '.[dev]'"
    if not CHROMIUM.exists():
        return f"no {CHROMIUM}: apt-get install -y chromium (no browser is ever downloaded)"
    return None


def start_api(services: BenchServices, database_url: str) -> tuple[str, Any, str]:
    """The api as a process (``bgrl up``'s :class:`Child`) on the bench's data folder and
    database, relaying the sim's frames; its URL, the child and an access token of its
    first admin from the login route (valid for a day). The admin's password derives from
    the service token, a secret of this run, so a second start on the same database signs
    in as the same admin."""
    import httpx

    from services.cli.serve import Child

    password = hashlib.sha256(f"bench-display:{services.token}".encode()).hexdigest()[:32]
    port = free_port()
    env = {
        "BGRL_DATA_DIR": str(services.folder),
        "BGRL_DATABASE_URL": database_url,
        "BGRL_SERVICE_TOKEN": services.token,
        "BGRL_SIM_URL": services.urls["sim"],
        "BGRL_EEG_URL": services.urls["eeg"],
        "BGRL_ADMIN_EMAIL": BENCH_ADMIN,
        "BGRL_ADMIN_PASSWORD": password,
        "BGRL_ACCESS_TOKEN_MINUTES": "1440",
        "BGRL_LOG_LEVEL": "WARNING",
    }
    cmd = [sys.executable, "-m", "uvicorn", "services.api.app:app", "--host", "127.0.0.1",
           "--port", str(port), "--no-access-log", "--log-level", "warning"]  # fmt: skip
    child = Child("api", cmd, env=env)
    child.start()
    url = f"http://127.0.0.1:{port}"
    try:
        wait_healthy(url)
        answer = httpx.post(
            f"{url}/api/v1/auth/token",
            data={"username": BENCH_ADMIN, "password": password},
            timeout=60,
        )
        answer.raise_for_status()
    except Exception:
        child.terminate()
        child.wait_or_kill(time.monotonic() + 10)
        raise
    return url, child, str(answer.json()["access_token"])


class DisplayError(RuntimeError):
    """The subject display could not be opened or stopped working."""


class DisplayPage:
    """The subject display page of one lab session, open in headless Chromium.

    Playwright drives the browser from a child process (:func:`display_child`), so that
    neither it nor the browser's messages take this process's interpreter from the runner
    whose latencies are measured. The page is signed in with an access token from the
    api's login route, kept in the tab's session storage as the sign-in form keeps it.
    """

    def __init__(self, api_url: str, access_token: str, session_id: int) -> None:
        root = str(Path(__file__).resolve().parents[1])
        path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)
        self.proc = subprocess.Popen(
            [sys.executable, "-c", "from benchmarks.bench_loop import display_child; "
             "display_child()"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
            env={**os.environ, "PYTHONPATH": path},
        )  # fmt: skip
        assert self.proc.stdin is not None
        config = {"api_url": api_url, "access_token": access_token, "session_id": session_id}
        self.proc.stdin.write(json.dumps(config) + "\n")
        self.proc.stdin.flush()
        opened = self._read(DISPLAY_OPEN_TIMEOUT_S)
        if not opened.get("ready"):
            self.proc.kill()
            self.proc.wait()
            raise DisplayError(opened.get("error", "the display page did not open"))

    def _read(self, timeout_s: float) -> dict[str, Any]:
        """The child's next message (``{"error": ...}`` if none came in time)."""
        assert self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout_s)
        line = self.proc.stdout.readline() if ready else ""
        if not line:
            why = "exited" if self.proc.poll() is not None else f"silent for {timeout_s:g} s"
            return {"error": f"the display's browser process {why}"}
        return dict(json.loads(line))

    def close(self) -> dict[str, Any]:
        """Close the page and the browser: ``console_errors`` the page logged,
        ``cpu_seconds`` of the browser and its driver, or ``error``."""
        try:
            out, _ = self.proc.communicate(input="stop\n", timeout=90)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            return {"error": "the display's browser process did not stop within 90 s"}
        except BrokenPipeError:  # it had exited
            out = self.proc.stdout.read() if self.proc.stdout is not None else ""
            self.proc.wait()
        lines = out.strip().splitlines()
        return dict(json.loads(lines[-1])) if lines else {"error": "the browser process exited"}


def display_child() -> None:
    """The child process of :class:`DisplayPage`: one JSON line in (``api_url``,
    ``access_token``, ``session_id``); ``{"ready": true}`` once the page is up, then, when a
    line or EOF arrives on stdin, the page's console errors and the CPU seconds of the
    browser and its driver (``{"error": ...}`` instead on a failure)."""
    config = json.loads(sys.stdin.readline())
    errors: list[str] = []

    def say(message: dict[str, Any]) -> None:
        print(json.dumps(message), flush=True)

    try:
        from playwright.sync_api import sync_playwright

        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(
                executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS
            )
            try:
                context = browser.new_context(
                    base_url=config["api_url"], viewport={"width": 1280, "height": 800}
                )
                token = json.dumps(config["access_token"])
                context.add_init_script(
                    script=f"sessionStorage.setItem('bgrl.access_token', {token});"
                )
                page = context.new_page()
                page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
                page.on("pageerror", lambda exc: errors.append(f"pageerror: {exc}"))
                page.goto(f"/sessions/{config['session_id']}/display")
                page.wait_for_selector("#display-frame", state="attached", timeout=60_000)
                say({"ready": True})
                while not select.select([sys.stdin], [], [], 0)[0]:
                    page.wait_for_timeout(250)  # Playwright handles the page's events meanwhile
            finally:
                browser.close()
    except Exception as exc:
        say({"error": f"{type(exc).__name__}: {exc}"})
        return
    used = [resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
    cpu = sum(u.ru_utime + u.ru_stime for u in used)
    say({"console_errors": errors[-20:], "cpu_seconds": round(cpu, 1)})


def _frames_reported(runtime: Any, run_id: int) -> int:
    """Frames the display reported for the run, once no new report came for
    :data:`FRAMES_SETTLE_S` (the page reports each frame after its marker row is read)."""
    from sqlalchemy import func, select

    from services.core.db.live import LiveFrameShown

    def count() -> int:
        with runtime.sessions() as db:
            return int(db.scalar(select(func.count()).where(LiveFrameShown.run_id == run_id)) or 0)

    last, since = count(), time.monotonic()
    while time.monotonic() - since < FRAMES_SETTLE_S:
        time.sleep(0.5)
        now = count()
        if now != last:
            last, since = now, time.monotonic()
    return last


def _sweep_spl(task: str, accuracy: float | None, labels: int, seeds: int) -> float | None:
    from services.learner.runs import HFPolicySpec, hf_policy_run

    if accuracy is None:
        return None
    spls = [
        hf_policy_run(HFPolicySpec(task, round(accuracy, 2), seed, labels))["greedy_spl"]
        for seed in range(seeds)
    ]
    return sum(spls) / len(spls)


def run_benchmark(
    out: Path,
    *,
    qualities: list[float],
    labels: int,
    calibration_actions: int,
    paced_actions: int,
    period_s: float,
    sweep_seeds: int,
    max_passes: int | None = None,
    display: bool = True,
) -> dict[str, Any]:
    """Run both parts (see the module docstring); returns and writes the result. Not
    ``display``: the paced session runs without the subject's display page (and the api)."""
    from services.worker.live_session import live_session

    out.mkdir(parents=True, exist_ok=True)
    tmp = tempfile.TemporaryDirectory(prefix="bgrl-bench-loop-")
    folder = Path(tmp.name)
    token = secrets.token_hex(16)
    urls, children = start_services(folder, token)
    for name, url in urls.items():
        os.environ[f"BGRL_{name.upper()}_URL"] = url
    os.environ["BGRL_SERVICE_TOKEN"] = token
    os.environ["BGRL_DATA_DIR"] = str(folder)
    runtime = job_runtime(folder)
    result: dict[str, Any] = {
        "synthetic": True,
        "cpus": os.cpu_count(),
        "load_average_1min_start": os.getloadavg()[0],
        "accelerated": [],
    }
    try:
        classifiers: dict[float, int] = {}
        for k, quality in enumerate(qualities):
            started = time.perf_counter()
            subject_id = _subject(runtime, f"BENCH-{k}-{secrets.token_hex(2)}")
            trained = _classifier(runtime, subject_id, quality, calibration_actions, max_passes)
            classifiers[quality] = trained["classifier_id"]
            session_id = lab_session(runtime, "online", subject_id)
            options = {
                "accelerated": True,
                "virtual_quality": quality,
                "classifier_id": trained["classifier_id"],
                "label_budget": labels,
            }
            run_id, job_id = live_run(runtime, session_id, "online", options)
            t, cpu_before = time.perf_counter(), cpu_seconds(children)
            online = run_to_end(runtime, job_id, live_session)
            online_s = time.perf_counter() - t
            cpu_per_label = _cpu_ms_per(cpu_before, cpu_seconds(children), online["labels"])
            accuracy = online["decoding_accuracy"]
            row = {
                "quality": quality,
                "classifier_test_accuracy": trained["metrics"].get("test_accuracy"),
                "live_decoding_accuracy": accuracy,
                "labels": online["labels"],
                "actions": online["actions"],
                "rejected": online["decoding_rejected"],
                "hf_policy_spl": online["hf_policy_spl"],
                "hf_sweep_spl_at_same_accuracy": _sweep_spl("sssg", accuracy, labels, sweep_seeds),
                "online_seconds": round(online_s, 1),
                "seconds_per_label": round(online_s / max(online["labels"], 1), 4),
                "cpu_ms_per_label": cpu_per_label,
                "latency_ms": run_latencies(runtime, run_id),
                "wall_seconds": round(time.perf_counter() - started, 1),
                "cpu_seconds_so_far": cpu_seconds(children),
            }
            result["accelerated"].append(row)
            print(json.dumps({k: v for k, v in row.items() if k != "latency_ms"}), flush=True)
        if paced_actions:
            subject_id = _subject(runtime, f"BENCH-PACED-{secrets.token_hex(2)}")
            quality = qualities[0]
            result["paced"] = paced_session(
                runtime,
                subject_id,
                classifiers[quality],
                quality=quality,
                actions=paced_actions,
                period_s=period_s,
                services=BenchServices(folder, token, urls, children),
                display=display,
            )
            print(json.dumps(result["paced"]), flush=True)
        result["load_average_1min_end"] = os.getloadavg()[0]
        result["cpu_seconds"] = cpu_seconds(children)
        (out / "loop.json").write_text(json.dumps(result, indent=2))
        if "paced" in result:
            plot_paced({"this run": result["paced"]}, out / "loop_paced.png")
        return result
    finally:
        deadline = time.monotonic() + 10
        for child in children:
            child.terminate()
        for child in children:
            child.wait_or_kill(deadline)
        runtime.engine.dispose()
        tmp.cleanup()


def _utc_now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


@dataclass
class BenchServices:
    """The services a bench started: data folder, service token, URLs and child processes
    (the api joins them when the display page needs it)."""

    folder: Path
    token: str
    urls: dict[str, str]
    children: list[Any]


def paced_session(
    runtime: Any,
    subject_id: int,
    classifier_id: int,
    *,
    quality: float,
    actions: int,
    period_s: float,
    services: BenchServices,
    display: bool = True,
) -> dict[str, Any]:
    """A paced online session of ``actions`` actions with the virtual subject in real time,
    watched on the subject's display page (unless not ``display``); its timeline
    (``latency_ms``), pace, CPU, wall-clock span and load average."""
    from services.worker.live_session import live_session

    started_at, load_start = _utc_now(), os.getloadavg()[0]
    session_id = lab_session(runtime, "online", subject_id)
    page, display_result = None, {"reason": "--no-display"}
    if display:
        page, display_result = _open_display(runtime, services, session_id)
    options = {"accelerated": False, "virtual_quality": quality, "classifier_id": classifier_id,
               "label_budget": actions, "n_actions": actions, "period_s": period_s}  # fmt: skip
    run_id, job_id = live_run(runtime, session_id, "online", options)
    cpu_before = cpu_seconds(services.children)
    try:
        online = run_to_end(runtime, job_id, live_session)
        cpu_after = cpu_seconds(services.children)
        if page is not None:
            display_result["frames_reported"] = _frames_reported(runtime, run_id)
    finally:
        if page is not None:
            display_result.update(page.close())
    latency = run_latencies(runtime, run_id)
    if page is None:  # no display page: no frame-shown figure, the reason instead
        latency.pop("marker_to_frame_shown", None)
    return {
        "utc": [started_at, _utc_now()],
        "load_average_1min": {"start": load_start, "end": os.getloadavg()[0]},
        "cpu_ms_per_action": _cpu_ms_per(cpu_before, cpu_after, online["actions"]),
        "actions": online["actions"],
        "labels": online["labels"],
        "period_s": period_s,
        "latency_ms": latency,
        "pace": _pace(runtime, run_id, period_s),
        "display": display_result,
    }


def _open_display(
    runtime: Any, services: BenchServices, session_id: int
) -> tuple[DisplayPage | None, dict[str, Any]]:
    """The api (added to the children) and the session's display page, opened before the
    session starts as a lab opens it; (None, the reason) where that is impossible here."""
    page = f"/sessions/{session_id}/display"
    reason = display_unavailable()
    if reason is not None:
        return None, {"page": page, "reason": reason}
    try:
        api_url, api, access_token = start_api(services, runtime.settings.resolved_database_url)
    except Exception as exc:
        return None, {"page": page, "reason": f"the api did not start: {exc}"}
    services.children.append(api)
    try:
        display = DisplayPage(api_url, access_token, session_id)
    except DisplayError as exc:
        return None, {"page": page, "reason": f"the display page did not open: {exc}"}
    return display, {"page": page, "browser": str(CHROMIUM)}


PLOTTED_LATENCIES = {
    "marker_to_frame_shown": "action -> frame shown",
    "marker_to_epoch_end": "marker -> epoch end",
    "epoch_end_to_decision": "epoch end -> decision",
    "decision_to_update": "decision -> update + next action",
    "epoch_end_to_next_action": "epoch end -> next action",
}


def plot_paced(runs: dict[str, dict[str, Any]], path: Path) -> None:
    """Bar chart of paced sessions' per-action latencies (p50 bars, p99 and max marks), one
    colour per run (``runs``: label -> a ``paced`` result of ``loop.json``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(PLOTTED_LATENCIES)
    fig, ax = plt.subplots(figsize=(10, 4.5))
    width = 0.8 / max(len(runs), 1)
    for k, (label, paced) in enumerate(runs.items()):
        legend: str | None = label
        for i, name in enumerate(names):
            figure = paced["latency_ms"].get(name)
            if not figure or figure["p50_ms"] is None:
                continue
            x = i + (k - (len(runs) - 1) / 2) * width
            ax.bar(x, figure["p50_ms"], width, color=f"C{k}", label=legend)
            legend = None
            ax.plot([x, x], [figure["p50_ms"], figure["p99_ms"]], color="black", linewidth=1)
            ax.plot(x, figure["p99_ms"], "_", color="black", markersize=10)
            ax.plot(x, figure["max_ms"], "x", color="grey", markersize=5)
    ax.set_xticks(range(len(names)), [PLOTTED_LATENCIES[n] for n in names], fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("ms per action (bar p50, dash p99, x max)")
    ax.set_title("paced session, virtual subject (SYNTHETIC EEG)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _cpu_ms_per(before: dict[str, float], after: dict[str, float], n: int) -> dict[str, float]:
    """CPU milliseconds per item of each process (``demo``: the runner's own) between two
    :func:`cpu_seconds` snapshots."""
    return {k: round(1000 * (after[k] - before.get(k, 0.0)) / max(n, 1), 2) for k in after}


def _pace(runtime: Any, run_id: int, period_s: float) -> dict[str, float | None]:
    from sqlalchemy import select

    from services.core.db.live import LiveMarker
    from services.core.live import pace_drift

    with runtime.sessions() as db:
        stamps = db.scalars(
            select(LiveMarker.marker_ts)
            .where(LiveMarker.run_id == run_id)
            .order_by(LiveMarker.step)
        ).all()
    return pace_drift(list(stamps), period_s)
