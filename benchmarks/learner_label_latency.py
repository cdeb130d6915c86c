"""Latency of one label in the learner service, part by part, as the live loop sends it.

Run: ``.venv/bin/python -m benchmarks.learner_label_latency [--labels 1000] [--method M]
[--prepared] [--out FILE]``. A session (the recommended stage-2 method unless ``--method``)
takes ``--labels`` labels, each with ``next_observation`` as the session runner sends them,
through the app (TestClient, so no network). For each label, the wall time and the CPU time
of the handling thread are measured for: the Fhat update (1 + K_HF steps, none for a
held-out label; with ``--prepared``, swapping the prepared update in), pi_HF's next action,
the journal entries, the metrics, the whole answer (the request up to its response), and
what runs after the answer (journal sync, and every ``checkpoint_every`` entries the
checkpoint). With ``--prepared`` each label is first prepared (``POST /labels/prepare``, as
the session runner does while the epoch is recorded; ``prepare`` is that request's handler,
``prepare_request`` the whole request). Prints p50/p99/max and the mean in ms as JSON, with
the load average (wall times grow with it on a shared machine; CPU times less so).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from fastapi.testclient import TestClient

from services.core.platform import PlatformSettings
from services.learner.hf_methods import RECOMMENDED_METHOD
from services.learner.service.app import create_app
from services.learner.service.settings import LearnerSettings

PARTS = ("prepare", "update", "next_action", "journal", "metrics", "after_answer")
OFF_ANSWER = ("prepare", "after_answer")
"""Parts outside the label's answer."""


def _observation(i: int) -> list[float]:
    return [float((i * 7 + k) % 13) for k in range(10)] + [1.0 + i % 11, 0.3 * (i % 7) - 1, 0.1]


def _stats(values: list[float]) -> dict[str, float]:
    ms = np.asarray(values) * 1e3
    return {
        "p50_ms": round(float(np.percentile(ms, 50)), 3),
        "p99_ms": round(float(np.percentile(ms, 99)), 3),
        "max_ms": round(float(ms.max()), 3),
        "mean_ms": round(float(ms.mean()), 3),
    }


class _Timer:
    """Wall and thread-CPU seconds of each call of the wrapped functions, summed per label."""

    def __init__(self) -> None:
        self.wall = {part: 0.0 for part in PARTS}
        self.cpu = {part: 0.0 for part in PARTS}

    def wrap(self, part: str, func: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            wall, cpu = time.perf_counter(), time.thread_time()
            try:
                return func(*args, **kwargs)
            finally:
                self.wall[part] += time.perf_counter() - wall
                self.cpu[part] += time.thread_time() - cpu

        return timed

    def take(self) -> tuple[dict[str, float], dict[str, float]]:
        taken = (dict(self.wall), dict(self.cpu))
        self.wall = {part: 0.0 for part in PARTS}
        self.cpu = {part: 0.0 for part in PARTS}
        return taken


def measure(
    n_labels: int, method: str = RECOMMENDED_METHOD, prepared: bool = False
) -> dict[str, object]:
    """Send ``n_labels`` labels to a fresh session (each prepared first if ``prepared``);
    per-label timings."""
    torch.set_num_threads(1)
    logging.disable(logging.INFO)  # the per-request log line is not what is measured
    timer = _Timer()
    wall: dict[str, list[float]] = {part: [] for part in (*PARTS, "answer", "prepare_request")}
    cpu: dict[str, list[float]] = {part: [] for part in (*PARTS, "answer")}
    n_prepared = 0
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp)
        settings = LearnerSettings(data_dir=data)
        app = create_app(settings, PlatformSettings(data_dir=data))
        with TestClient(app) as client:
            created = client.post(
                "/hf-sessions", json={"label_budget": n_labels + 1, "method": method}
            )
            sid = created.json()["id"]
            store = app.state.store
            session = store.get(sid)
            session.add_label = timer.wrap("update", session.add_label)
            session.add_forked_label = timer.wrap("update", session.add_forked_label)
            store.prepare_label = timer.wrap("prepare", store.prepare_label)
            session.act = timer.wrap("next_action", session.act)
            session.metrics = timer.wrap("metrics", session.metrics)
            journal = store._journals[sid]
            journal.append = timer.wrap("journal", journal.append)
            store.persist = timer.wrap("after_answer", store.persist)
            for i in range(n_labels):
                fields = {
                    "marker_id": f"m{i}",
                    "observation": _observation(i),
                    "action": i % 3,
                    "next_observation": _observation(i + 1),
                }
                if prepared:
                    started = time.perf_counter()
                    answer = client.post(f"/hf-sessions/{sid}/labels/prepare", json=fields)
                    wall["prepare_request"].append(time.perf_counter() - started)
                    answer.raise_for_status()
                fields["feedback"] = "correct" if i % 2 else "error"
                started = time.perf_counter()
                response = client.post(f"/hf-sessions/{sid}/labels", json=fields)
                request = time.perf_counter() - started
                response.raise_for_status()
                n_prepared += response.json()["prepared"]
                part_wall, part_cpu = timer.take()
                for part in PARTS:
                    wall[part].append(part_wall[part])
                    cpu[part].append(part_cpu[part])
                # TestClient returns after the background task: the answer is the rest
                wall["answer"].append(request - part_wall["after_answer"])
                cpu["answer"].append(sum(part_cpu[p] for p in PARTS if p not in OFF_ANSWER))
            size = (store.root / sid / "state.pt").stat().st_size
    logging.disable(logging.NOTSET)
    return {
        "labels": n_labels,
        "method": method,
        "prepared": n_prepared,
        "checkpoint_every": settings.checkpoint_every,
        "load_average_1min": os.getloadavg()[0],
        "cpu_count": os.cpu_count(),
        "checkpoint_bytes_at_end": size,
        "wall": {part: _stats(values) for part, values in wall.items() if values},
        "thread_cpu": {part: _stats(values) for part, values in cpu.items()},
        "notes": "answer wall = the request minus what runs after the answer (TestClient "
        "returns after it); answer thread_cpu = update + next_action + journal + metrics; "
        "prepare (with --prepared) is the POST /labels/prepare before the label",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--labels", type=int, default=1000)
    parser.add_argument("--method", default=RECOMMENDED_METHOD)
    parser.add_argument(
        "--prepared", action="store_true", help="prepare each label first (POST /labels/prepare)"
    )
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    result = json.dumps(measure(args.labels, args.method, args.prepared), indent=2)
    if args.out:
        args.out.write_text(result + "\n")
    print(result)


if __name__ == "__main__":
    main()
