"""``bgrl bench loop``: the closed loop's timing and learning with the virtual subject.

1. Accelerated, per virtual-subject quality: a calibration session, its classifier, then an
   online session of ``labels`` labels through the sim, EEG and learner services; reported:
   the classifier's held-out accuracy, the live decoding accuracy vs the oracle, pi_HF's SPL,
   and beside it ``bgrl hf-sweep``'s pi_HF SPL (simulated feedback) at the same accuracy.
2. Paced (one action every ``period_s`` on the wall clock, the virtual subject streaming in
   real time): the per-action timeline from the rows (marker -> epoch end, epoch end ->
   decision, decision -> learner update, update -> next action ready, epoch end -> next action
   ready) as p50/p99, and the pace's drift.

Writes ``OUT/loop.json``.
"""

from __future__ import annotations

import json
import os
import secrets
import tempfile
import time
from pathlib import Path
from typing import Any

from services.cli.demo import (
    _lab_session,
    _live_run,
    _run,
    cpu_seconds,
    job_runtime,
    run_latencies,
    start_services,
)


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

    session_id = _lab_session(runtime, "calibration", subject_id)
    options: dict[str, Any] = {
        "accelerated": True,
        "virtual_quality": quality,
        "n_actions": actions,
    }
    if max_passes is not None:
        options["calibration_max_passes"] = max_passes
    _, job_id = _live_run(runtime, session_id, "calibration", options)
    calibration = _run(runtime, job_id, live_session)
    return _run(runtime, calibration["calibration_job_id"], eeg_calibration)


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
) -> dict[str, Any]:
    """Run both parts (see the module docstring); returns and writes the result."""
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
            session_id = _lab_session(runtime, "online", subject_id)
            options = {
                "accelerated": True,
                "virtual_quality": quality,
                "classifier_id": trained["classifier_id"],
                "label_budget": labels,
            }
            run_id, job_id = _live_run(runtime, session_id, "online", options)
            t, cpu_before = time.perf_counter(), cpu_seconds(children)
            online = _run(runtime, job_id, live_session)
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
            session_id = _lab_session(runtime, "online", subject_id)
            options = {"accelerated": False, "virtual_quality": quality,
                       "classifier_id": classifiers[quality], "label_budget": paced_actions,
                       "n_actions": paced_actions, "period_s": period_s}  # fmt: skip
            run_id, job_id = _live_run(runtime, session_id, "online", options)
            cpu_before = cpu_seconds(children)
            online = _run(runtime, job_id, live_session)
            result["paced"] = {
                "cpu_ms_per_action": _cpu_ms_per(
                    cpu_before, cpu_seconds(children), online["actions"]
                ),
                "actions": online["actions"],
                "labels": online["labels"],
                "period_s": period_s,
                "latency_ms": run_latencies(runtime, run_id),
                "pace": _pace(runtime, run_id, period_s),
            }
            print(json.dumps(result["paced"]), flush=True)
        result["load_average_1min_end"] = os.getloadavg()[0]
        result["cpu_seconds"] = cpu_seconds(children)
        (out / "loop.json").write_text(json.dumps(result, indent=2))
        return result
    finally:
        deadline = time.monotonic() + 10
        for child in children:
            child.terminate()
        for child in children:
            child.wait_or_kill(deadline)
        runtime.engine.dispose()
        tmp.cleanup()


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
