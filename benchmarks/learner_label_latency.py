"""Latency of one label in the learner service: Fhat's update plus the atomic checkpoint.

Run: ``.venv/bin/python -m benchmarks.learner_label_latency [--labels 1000] [--out FILE]``.
A session with the paper's Fhat settings takes ``--labels`` labels; for each, the wall time
and the CPU time of the thread are measured for the update (1 + K_HF steps, or none for a
held-out label), the checkpoint (serialise + write + fsync + rename), and the whole HTTP
request through the app (TestClient, so no network). Prints p50/p99/max in ms as JSON, with
the machine's load average (wall times grow with it on a shared machine; CPU times less so).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from fastapi.testclient import TestClient

from services.core.platform import PlatformSettings
from services.learner.service.app import create_app
from services.learner.service.settings import LearnerSettings


def _observation(i: int) -> list[float]:
    return [float((i * 7 + k) % 13) for k in range(10)] + [1.0 + i % 11, 0.3 * (i % 7) - 1, 0.1]


def _stats(values: list[float]) -> dict[str, float]:
    ms = np.asarray(values) * 1e3
    return {
        "p50_ms": round(float(np.percentile(ms, 50)), 2),
        "p99_ms": round(float(np.percentile(ms, 99)), 2),
        "max_ms": round(float(ms.max()), 2),
    }


def measure(n_labels: int) -> dict[str, object]:
    """Send ``n_labels`` labels to a fresh session; per-label timings."""
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp)
        app = create_app(LearnerSettings(data_dir=data), PlatformSettings(data_dir=data))
        with TestClient(app) as client:
            sid = client.post("/hf-sessions", json={"label_budget": n_labels}).json()["id"]
            store = app.state.store
            session = store.get(sid)
            timings: dict[str, list[float]] = {k: [] for k in ("update", "checkpoint", "http")}
            cpu: dict[str, list[float]] = {k: [] for k in ("update", "checkpoint")}
            original = store.checkpoint

            def timed_checkpoint(s):  # the update is the rest of add_label
                wall, thread = time.perf_counter(), time.thread_time()
                original(s)
                timings["checkpoint"].append(time.perf_counter() - wall)
                cpu["checkpoint"].append(time.thread_time() - thread)

            store.checkpoint = timed_checkpoint
            original_add = session.add_label

            def timed_add(**label):
                wall, thread = time.perf_counter(), time.thread_time()
                outcome = original_add(**label)
                timings["update"].append(time.perf_counter() - wall)
                cpu["update"].append(time.thread_time() - thread)
                return outcome

            session.add_label = timed_add
            for i in range(n_labels):
                started = time.perf_counter()
                response = client.post(
                    f"/hf-sessions/{sid}/labels",
                    json={
                        "marker_id": f"m{i}",
                        "observation": _observation(i),
                        "action": i % 3,
                        "feedback": "correct" if i % 2 else "error",
                    },
                )
                timings["http"].append(time.perf_counter() - started)
                response.raise_for_status()
            size = (store.root / sid / "state.pt").stat().st_size
    label_wall = [u + c for u, c in zip(timings["update"], timings["checkpoint"], strict=True)]
    label_cpu = [u + c for u, c in zip(cpu["update"], cpu["checkpoint"], strict=True)]
    return {
        "labels": n_labels,
        "load_average_1min": os.getloadavg()[0],
        "cpu_count": os.cpu_count(),
        "checkpoint_bytes_at_end": size,
        "wall": {
            "update": _stats(timings["update"]),
            "checkpoint": _stats(timings["checkpoint"]),
            "label_plus_checkpoint": _stats(label_wall),
            "http_request": _stats(timings["http"]),
        },
        "thread_cpu": {
            "update": _stats(cpu["update"]),
            "checkpoint": _stats(cpu["checkpoint"]),
            "label_plus_checkpoint": _stats(label_cpu),
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--labels", type=int, default=1000)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    result = json.dumps(measure(args.labels), indent=2)
    if args.out:
        args.out.write_text(result + "\n")
    print(result)


if __name__ == "__main__":
    main()
